"""Table cells keep their tokens whole: a number, a ratio, a word is never broken over two
lines on the report, validate, compare and audit pages at 900 and 1400 px.

Each page is opened in headless Chromium (:mod:`support.browser`) and every table cell is
measured (:data:`support.browser.TOKEN_PROBE`: a Range over each whitespace-free token;
more than one line of client rects means the browser split it). A cell may wrap between
words; a table too wide for the page scrolls inside its wrapper. ``overflow-wrap: anywhere``
on the cells made ``832.00/18``, ``18/4`` over ``2``, ``mo/del``, ``condit/ion``, ``o/k``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support.browser import CHROMIUM, probe_pages
from support.demo_run import make_demo_run

pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="chromium not installed (.ci/run installs it)"
)

WIDTHS = (900, 1400)
#: the pages measured (the ``pages`` fixture builds them)
PAGES = ("report", "report-models", "validate", "compare", "audit")


def _audit_page(work: Path) -> Path:
    """``vtcal audit`` of a small fleet: robot A re-recorded after joint 3's zero turned,
    robot B of the same model once (so the robots-compared table is there too)."""
    from pipeline.cli import main
    from pipeline.sim.history import Event, make_history, write_history

    hist = make_history(
        "A", {1: Event("joint_offset", np.radians(0.05), "joint_3")}, seed=11,
        n_recordings=2, per_target=8,
    )  # fmt: skip
    hist += make_history("B", {}, seed=12, n_recordings=1, per_target=8)
    write_history(hist, work / "runs")
    try:
        main(
            ["audit", str(work / "runs"), "--out", str(work / "audit"), "--models", "offsets,full"]
        )
    except SystemExit as exc:
        assert not exc.code, exc.code
    return work / "audit" / "audit.html"


@pytest.fixture(scope="module")
def pages(lrmate_run: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every page with tables: the report of a synthetic run (targets, parameters, stages,
    files) and of a real identification (the error models with their condition numbers),
    validate.html, compare.html of the two runs, audit.html."""
    from pipeline.accuracy.compare import compare_runs, render_html
    from pipeline.cli import main
    from pipeline.report.html import build_report

    tmp = tmp_path_factory.mktemp("tokens")
    demo = make_demo_run(tmp / "demo", seed=3)
    out = {
        "report": build_report(demo, tmp / "report.html"),
        "report-models": build_report(lrmate_run, tmp / "models.html"),
    }
    table = tmp / "other.csv"  # the same touch-ups in another order: not the fitted file
    rows = (lrmate_run.parent / "table.csv").read_text().splitlines()
    table.write_text("\n".join([rows[0], *rows[:0:-1]]) + "\n")
    try:
        main(["validate", str(lrmate_run / "calibrated.urdf"), str(table),
              "--urdf", str(lrmate_run.parent / "nominal.urdf"), "--out", str(tmp / "val")])  # fmt: skip
    except SystemExit as exc:
        assert exc.code in (0, 3), exc.code
    out["validate"] = tmp / "val" / "validate.html"
    cmp = tmp / "compare.html"
    cmp.write_text(render_html(compare_runs([demo, lrmate_run])))
    out["compare"] = cmp
    out["audit"] = _audit_page(tmp)
    return out


@pytest.fixture(scope="module")
def probed(
    pages: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> dict[tuple[str, int], dict]:
    """Every page at both widths, measured in one browser."""
    return probe_pages(pages, tmp_path_factory.mktemp("chromium"), WIDTHS)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("page", PAGES)
def test_table_cells_keep_their_tokens_whole(probed: dict, page: str, width: int) -> None:
    """No token of any table cell spans two lines; the page itself never scrolls sideways
    (a table too wide scrolls inside its ``.table-wrap``)."""
    lay, tok = probed[(page, width)]["layout"], probed[(page, width)]["tokens"]
    assert tok["cells"] > 10, (page, width, "table cells not measured", tok)
    broken = [f"{b['token']!r} over {b['lines']} lines in {b['cell']}" for b in tok["broken"]]
    assert not broken, f"{len(broken)} token(s) broken on {page} at {width} px:\n" + "\n".join(
        broken
    )
    assert lay["page"] <= lay["viewport"], (page, width, lay)


@pytest.mark.parametrize("page", PAGES)
def test_no_console_error_on_any_page(probed: dict, page: str) -> None:
    """A page opened as a user opens it logs no error: its icon, styles and images are
    allowed by its own content policy (the validate page's icon once was not)."""
    errors = [e for w in WIDTHS for e in probed[(page, w)]["errors"]]
    assert not errors, (page, errors)
