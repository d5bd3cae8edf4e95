"""report.html: content from a synthetic run folder, and a headless-Chromium check that it
opens offline (no request leaves the file, no console error), with a screenshot
(:mod:`support.browser`: DevTools protocol over a pipe).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from support.browser import CHROMIUM, open_in_chromium
from support.demo_run import make_demo_run

from pipeline.report.data import load_run
from pipeline.report.figures import nominal_fit
from pipeline.report.html import build_report


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_demo_run(tmp_path_factory.mktemp("run") / "run", seed=3)


@pytest.fixture(scope="module")
def report(demo_run: Path) -> Path:
    return build_report(demo_run)


# ------------------------------------------------------------------------ tests

needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="chromium not installed (.ci/run installs it)"
)


@needs_chromium
def test_report_opens_offline_without_errors(report: Path, tmp_path: Path) -> None:
    shot = report.parent / "report.png"
    res = open_in_chromium(report, tmp_path, screenshot=shot)
    assert res["leaving"] == [], res["leaving"]
    assert res["errors"] == [], res["errors"]
    assert "vtcal report" in res["title"]
    assert res["n_svg"] >= 5  # residuals, per target, targets, convergence, cross-validation, ...
    png = shot.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


@needs_chromium
def test_checker_sees_a_request_leaving(report: Path, tmp_path: Path) -> None:
    """Negative control: a page that fetches from outside is caught (request or CSP error)."""
    html = report.read_text()
    bad = tmp_path / "bad.html"
    bad.write_text(html.replace("</main>", '<img src="http://127.0.0.1:9/x.png"></main>'))
    res = open_in_chromium(bad, tmp_path)
    assert res["leaving"] or res["errors"]
    # and without our CSP the request itself is seen
    bare = tmp_path / "bare.html"
    bare.write_text('<html><body><img src="http://127.0.0.1:9/x.png"></body></html>')
    res = open_in_chromium(bare, tmp_path)
    assert any("127.0.0.1:9" in u for u in res["leaving"])


def test_report_content(report: Path) -> None:
    html = report.read_text()
    # verdict at the top, before any section below it
    assert html.index("Verdict") < html.index('id="residuals"')
    for text in (
        "lrmate200id_like",
        "recording.mcap",
        "2026-09-21",  # date from the recording stamps
        "NOT identifiable",  # scale held, said plainly
        "captured while moving",
        "not converged",
        "data:image/png;base64,",  # thumbnails: the recording is reachable
        "Touch-up convergence",
        "Cross-validation",
        "predicted shape accuracy",
        "not reachable: no known distance",  # absolute accuracy needs a known distance
        "held at their nominal value",
        "along the base frame&#39;s z: not observable",  # why joint_1.z was held
        "inferred by the pipeline",  # what the metadata did not say, at the top
        "dark_on_light (automatic",
    ):
        assert text in html, text
    # nothing that would fetch: no external src/href/url(), no script
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:|//|file:)""", html)
    assert not re.search(r"url\(\s*[\"']?\s*(https?:|//)", html)
    assert "<script" not in html
    assert "Content-Security-Policy" in html


def test_report_is_deterministic_and_small(demo_run: Path, report: Path, tmp_path: Path) -> None:
    a = report.read_bytes()
    b = build_report(demo_run, tmp_path / "b.html").read_bytes()
    assert a == b
    assert len(a) < 5_000_000


def test_report_without_recording_or_identification(tmp_path: Path) -> None:
    """Missing artefacts and an unreachable recording give 'not available', not a crash."""
    run = make_demo_run(tmp_path / "run", seed=1, with_recording=False)
    for f in ("parameters.parquet", "residuals.parquet", "crossval.parquet", "identify.json"):
        (run / f).unlink()
    html = build_report(run).read_text()
    assert "not available" in html
    assert "data:image/png" not in html
    assert "not reachable" in html


def test_nominal_fit_recovers_exact_pin_and_targets(tmp_path: Path) -> None:
    """With the true robot as 'nominal', the linear pin/target fit leaves ~zero residual."""
    run = make_demo_run(tmp_path / "run", seed=2, with_recording=False)
    data = load_run(run)
    # replace the nominal URDF by the calibrated (true) one without the pin link
    assert data.recording is not None and data.calibrated_urdf is not None
    data.recording["urdf"] = data.calibrated_urdf
    res = nominal_fit(data)
    assert res is not None and len(res) >= 6
    assert float(np.max(res["norm"])) < 1e-9
    # the real nominal robot leaves a clearly larger residual
    res_nom = nominal_fit(load_run(run))
    assert res_nom is not None and float(np.sqrt(np.mean(res_nom["norm"] ** 2))) > 1e-5


def test_report_of_an_identify_only_folder(tmp_path: Path) -> None:
    """What `vtcal identify` leaves (no recording.json, no touch-up tables) still reports."""
    run = make_demo_run(tmp_path / "run", seed=4, with_recording=False)
    for f in (
        "recording.json",
        "touchups.parquet",
        "inliers.parquet",
        "frames.parquet",
        "detections.parquet",
        "run.json",
    ):
        (run / f).unlink()
    data = load_run(run)
    assert data.base_link == "base_link" and data.flange_link == "flange"  # from calibrated.urdf
    html = build_report(run).read_text()
    assert "fit residual, model full" in html
    assert "Touch-ups not available" in html


def test_report_with_a_known_distance_says_the_scale_was_identified(tmp_path: Path) -> None:
    run = make_demo_run(tmp_path / "run", seed=6, with_recording=False, known_distance=True)
    html = build_report(run).read_text()
    assert "length scale was identified" in html
    assert "NOT identifiable" not in html
    assert "not reachable: no known distance" not in html


def test_thumbnails_stay_within_their_byte_budget(
    demo_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pipeline.report.html as report_html

    monkeypatch.setattr(report_html, "THUMB_BUDGET", 1)
    html = build_report(demo_run, tmp_path / "r.html").read_text()
    assert "data:image/png" not in html
    assert "left out to keep the file small" in html


# ------------------------------------------------------------ layout (issue 35)


def _points(svg: str) -> list[tuple[float, float]]:
    """Every dot (``Mx yh0``) of an SVG."""
    return [(float(x), float(y)) for x, y in re.findall(r"M([-\d.]+) ([-\d.]+)h0", svg)]


def _legend_box(svg: str) -> tuple[float, float, float, float]:
    m = re.search(
        r'<rect x="([-\d.]+)" y="([-\d.]+)" width="([\d.]+)" height="([\d.]+)" fill="white"', svg
    )
    assert m, "no legend"
    x, y, w, h = map(float, m.groups())
    return x, y, x + w, y + h


def test_the_per_target_legend_covers_no_data() -> None:
    """The legend sat over the last target's bar and top point; it sits above the axes now."""
    from pipeline.report import plots

    rng = np.random.default_rng(0)
    values = {
        "nominal": [rng.uniform(0.5, 1.0, 6), rng.uniform(0.5, 1.0, 6), np.r_[1.3, 0.9, 1.0]],
        "full": [rng.uniform(0, 0.05, 6) for _ in range(3)],
    }
    svg = plots.per_target(["0", "1", "2"], values, "residual (mm)")
    x0, y0, x1, y1 = _legend_box(svg)
    pts = _points(svg)
    legend_dots = [(x, y) for x, y in pts if x0 <= x <= x1 and y0 <= y <= y1]
    data = [p for p in pts if p not in legend_dots]
    assert len(legend_dots) == 2, legend_dots  # only the keys' own dots
    assert len(data) == 15 + 18
    assert min(y for _, y in data) > y1, "a data point under the legend"


def test_all_empty_target_columns_are_not_shown(lrmate_run: Path) -> None:
    """The print-shape columns (all '-' when no print shape was fitted) pushed the targets
    table past the page; they are named under it instead."""
    import pandas as pd

    tg = pd.read_parquet(lrmate_run / "targets.parquet")
    empty = [c for c in tg.columns if tg[c].isna().all()]
    assert empty, "the run has all-empty target columns to hide"
    html = build_report(lrmate_run, lrmate_run / "layout.html").read_text()
    section = html[html.index('<section id="targets">') : html.index('<section id="parameters">')]
    for c in empty:
        assert f"<th>{c}" not in section, c
    assert "Not shown, without a value for any target: " + ", ".join(empty) in section


def _pages(demo_run: Path, lrmate_run: Path, tmp: Path) -> dict[str, Path]:
    """report.html of the demo run and of a real identification, validate.html, compare.html."""
    from pipeline.accuracy.compare import compare_runs, render_html
    from pipeline.cli import main

    pages = {
        "report": build_report(demo_run, tmp / "demo.html"),
        "report-models": build_report(lrmate_run, tmp / "models.html"),
    }
    val = tmp / "val"
    table = tmp / "other.csv"  # the same touch-ups in another order: not the fitted file
    rows = (lrmate_run.parent / "table.csv").read_text().splitlines()
    table.write_text("\n".join([rows[0], *rows[:0:-1]]) + "\n")
    try:
        main(["validate", str(lrmate_run / "calibrated.urdf"), str(table),
              "--urdf", str(lrmate_run.parent / "nominal.urdf"), "--out", str(val)])  # fmt: skip
    except SystemExit as exc:
        assert exc.code in (0, 3), exc.code
    pages["validate"] = val / "validate.html"
    cmp = tmp / "compare.html"
    cmp.write_text(render_html(compare_runs([demo_run, lrmate_run])))
    pages["compare"] = cmp
    return pages


@needs_chromium
@pytest.mark.parametrize("width", [900, 1400])
def test_the_pages_fit_the_window(demo_run: Path, lrmate_run: Path, tmp_path: Path, width: int):
    """No sideways scrolling, nothing cut off, no SVG text over other text at 900 and 1400 px
    (the targets table was 1354 px wide at 900, cut off at 1400)."""
    for name, page in _pages(demo_run, lrmate_run, tmp_path).items():
        res = open_in_chromium(page, tmp_path / f"{name}-{width}", width=width)
        lay = res["layout"]
        assert lay["page"] <= lay["viewport"], (name, lay)
        assert lay["past"] == [] and lay["scrolls"] == [], (name, lay)
        assert lay["overlaps"] == [], (name, lay)
