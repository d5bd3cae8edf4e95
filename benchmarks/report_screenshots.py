"""Screenshots of report.html, validate.html, the compare page and the audit page at 900 and
1400 px, with what the layout and token probes found.

    python benchmarks/report_screenshots.py [--run runs/sample] [--out docs/img] [--pages audit]

Runs the shipped sample (or takes a run folder of it), validates its calibration on its
own touch-ups in reverse order written as a table (a layout check, not a validation:
those are the touch-ups it was fitted on), compares the run with itself, and audits a
small simulated fleet: three LR Mate-like robots of six recordings each
(:mod:`pipeline.sim.history`, touch-up level): robot A's joint 3 zero turned 0.05 deg
before recording 2, its base moved 1 mm before recording 4 and its joint 2 zero turned
0.15 deg before its last; robot B's camera remounted (0.1 mm) before its last; robot C
unchanged; and robot D, three recordings 200 days older, overdue. Opens each page in headless Chromium
(``tests/support/browser.py``) at both widths, saves the first 1200 px of each as
``PAGE-WIDTH.png`` (and the first 1600 px of the page of the robot on top of the audit's
fleet page at 1400 px, ``audit-robot-1400.png``) and prints what the layout probe found
and how many table-cell tokens the token probe saw broken over two lines (docs/report.md).
``--pages``
takes some of report, validate, compare, audit (comma-separated; the sample is run only
for the first three).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))

#: the audited fleet: robot -> (seed, {recording index: (event kind, size, joint)},
#: recordings, days its first recording is before the others')
FLEET = {
    "A": (1, {2: ("joint_offset", np.radians(0.05), "joint_3"), 4: ("base", 1e-3, ""),
              5: ("joint_offset", np.radians(0.15), "joint_2")}, 6, 0),
    "B": (2, {5: ("camera", 1e-4, "")}, 6, 0),
    "C": (3, {}, 6, 0),
    "D": (4, {}, 3, 200),
}  # fmt: skip
#: how much of each page the screenshot keeps (CSS px)
HEIGHT = {"audit-robot": 1600}


def _audit(work: Path) -> Path:
    """``vtcal audit`` of :data:`FLEET` with an interval 30 days longer than the time since
    the first recordings of A, B and C (D's is 200 days older: overdue); its ``audit.html``."""
    import time

    from pipeline.cli import main
    from pipeline.sim.history import DAY_NS, START_NS, Event, make_history, write_history

    for rid, (seed, events, n, early) in FLEET.items():
        ev = {i: Event(k, s, j) for i, (k, s, j) in events.items()}
        hist = make_history(
            f"cell-{rid}", ev, seed=seed, n_recordings=n, start_ns=START_NS - early * DAY_NS
        )
        write_history(hist, work / "runs")
    interval = (time.time_ns() - START_NS) // DAY_NS + 30
    try:
        main(["audit", str(work / "runs"), "--out", str(work / "audit"),
              "--interval-days", str(interval)])  # fmt: skip
    except SystemExit as exc:
        if exc.code:
            raise
    return work / "audit" / "audit.html"


def _first_robot(fleet: Path) -> Path:
    """The page of the robot on top of the fleet page (the one to look at first)."""
    import re

    return fleet.parent / re.findall(r'<a href="(robots/[^"]+)"', fleet.read_text())[0]


#: the pages, in the order they are written
PAGES = ("report", "validate", "compare", "audit")


def _run_pages(run: Path, work: Path) -> dict[str, Path]:
    """report.html of the sample's run, validate.html, the compare page."""
    import pandas as pd

    from pipeline.accuracy.compare import compare_runs, render_html
    from pipeline.cli import main
    from pipeline.report.html import build_report

    rec = json.loads((run / "recording.json").read_text())
    names = list(rec["joint_names"])
    inl = pd.read_parquet(run / "inliers.parquet")
    inl = inl[inl["inlier"].astype(bool)]
    table = work / "touchups_reversed.csv"
    inl[["touchup_id", "target_id", *names]].iloc[::-1].to_csv(table, index=False)
    nominal = work / "nominal.urdf"
    nominal.write_text(rec["urdf"])
    val = work / "validate"
    try:
        main(["validate", str(run / "calibrated.urdf"), str(table), "--urdf", str(nominal),
              "--out", str(val)])  # fmt: skip
    except SystemExit as exc:
        if exc.code not in (0, 3):
            raise
    compare = work / "compare.html"
    compare.write_text(render_html(compare_runs([run])))
    return {
        "report": build_report(run, work / "report.html"),
        "validate": val / "validate.html",
        "compare": compare,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, default=None, help="run folder of the shipped sample")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    ap.add_argument("--pages", default=",".join(PAGES), help="comma-separated: " + ", ".join(PAGES))
    args = ap.parse_args(argv)
    wanted = [p for p in PAGES if p in args.pages.split(",")]
    from support.browser import CHROMIUM, open_in_chromium

    if CHROMIUM is None:
        sys.exit("chromium not installed (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pages: dict[str, Path] = {}
        run = args.run
        if run is None and set(wanted) - {"audit"}:
            from pipeline.cli import main as vtcal

            run = work / "sample"
            try:
                vtcal(["run", str(REPO / "datasets/samples/sample_lrmate.mcap"), "--out",
                       str(run), "-q"])  # fmt: skip
            except SystemExit as exc:
                if exc.code:
                    raise
        if run is not None:
            pages.update(_run_pages(run, work))
        if "audit" in wanted:
            pages["audit"] = _audit(work)
            pages["audit-robot"] = _first_robot(pages["audit"])
            wanted.append("audit-robot")
        args.out.mkdir(parents=True, exist_ok=True)
        for name in wanted:
            page = pages[name]
            for width in (900, 1400) if name != "audit-robot" else (1400,):
                shot = args.out / f"{name}-{width}.png"
                res = open_in_chromium(page, work / f"b-{name}-{width}", shot, width=width,
                                       height=HEIGHT.get(name, 1200))  # fmt: skip
                lay, tok = res["layout"], res["tokens"]
                for e in res["errors"]:
                    print("  browser:", e)
                for o in lay["overlaps"]:
                    print("  overlap:", o)
                for b in tok["broken"]:
                    print(f"  broken: {b['token']!r} over {b['lines']} lines in {b['cell']}")
                print(
                    f"{shot.relative_to(REPO) if shot.is_relative_to(REPO) else shot}: "
                    f"page {lay['page']} px in a {lay['viewport']} px window, "
                    f"{len(lay['past'])} element(s) past its edge, {len(lay['scrolls'])} "
                    f"table(s) scrolling, {len(lay['overlaps'])} text overlap(s); tokens: "
                    f"{len(tok['broken'])} of {tok['tokens']} in {tok['cells']} table cells "
                    f"broken over two lines; {len(res['leaving'])} request(s) leaving, "
                    f"{len(res['errors'])} error(s); {shot.stat().st_size // 1024} KiB"
                )


if __name__ == "__main__":
    main()
