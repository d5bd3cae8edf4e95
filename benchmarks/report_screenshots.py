"""Screenshots of report.html, validate.html and the compare page at 900 and 1400 px.

    python benchmarks/report_screenshots.py [--run runs/sample] [--out docs/img]

Runs the shipped sample (or takes a run folder of it), validates its calibration on its
own touch-ups in reverse order written as a table (a layout check, not a validation:
those are the touch-ups it was fitted on), compares the run with itself, opens each page
in headless Chromium (``tests/support/browser.py``) at both widths, saves the first
1200 px of each as ``PAGE-WIDTH.png`` and prints what the layout probe found (docs/report.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))


def _pages(run: Path, work: Path) -> dict[str, Path]:
    import pandas as pd

    from pipeline.cli import main
    from pipeline.compare import compare_runs, render_html
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, default=None, help="run folder of the shipped sample")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    args = ap.parse_args()
    from support.browser import CHROMIUM, open_in_chromium

    if CHROMIUM is None:
        sys.exit("chromium not installed (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        run = args.run
        if run is None:
            from pipeline.cli import main as vtcal

            run = work / "sample"
            try:
                vtcal(["run", str(REPO / "datasets/samples/sample_lrmate.mcap"), "--out",
                       str(run), "-q"])  # fmt: skip
            except SystemExit as exc:
                if exc.code:
                    raise
        args.out.mkdir(parents=True, exist_ok=True)
        for name, page in _pages(run, work).items():
            for width in (900, 1400):
                shot = args.out / f"{name}-{width}.png"
                res = open_in_chromium(page, work / f"b-{name}-{width}", shot, width=width,
                                       height=1200)  # fmt: skip
                lay = res["layout"]
                print(
                    f"{shot.relative_to(REPO) if shot.is_relative_to(REPO) else shot}: "
                    f"page {lay['page']} px in a {lay['viewport']} px window, "
                    f"{len(lay['past'])} element(s) past its edge, {len(lay['scrolls'])} "
                    f"table(s) scrolling, {len(lay['overlaps'])} text overlap(s); "
                    f"{shot.stat().st_size // 1024} KiB"
                )


if __name__ == "__main__":
    main()
