"""Screenshot of the audit page (``vtcal audit``) on a small simulated fleet, at 1400 px.

    python benchmarks/audit_screenshot.py [--out docs/img]

Three LR Mate-like robots of six recordings each (:mod:`pipeline.sim.history`,
touch-up level): robot A's joint 3 zero turned 0.05 deg before recording 2 and
its base moved 1 mm before recording 4; robot B's camera remounted (0.1 mm)
before recording 3; robot C unchanged. Audits them, opens ``audit.html`` in
headless Chromium (``tests/support/browser.py``) and saves ``audit-1400.png``
(the first 2400 px) and prints what the layout probe found.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

FLEET = {
    "A": (1, {2: ("joint_offset", np.radians(0.05), "joint_3"), 4: ("base", 1e-3, "")}),
    "B": (2, {3: ("camera", 1e-4, "")}),
    "C": (3, {}),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    args = ap.parse_args()
    from support.browser import CHROMIUM, open_in_chromium

    from pipeline.cli import main as vtcal
    from pipeline.sim.history import Event, make_history, write_history

    if CHROMIUM is None:
        sys.exit("chromium not installed (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for rid, (seed, events) in FLEET.items():
            ev = {i: Event(k, s, j) for i, (k, s, j) in events.items()}
            write_history(make_history(f"cell-{rid}", ev, seed=seed), work / "runs")
        try:
            vtcal(["audit", str(work / "runs"), "--out", str(work / "audit")])
        except SystemExit as exc:
            if exc.code:
                raise
        args.out.mkdir(parents=True, exist_ok=True)
        shot = args.out / "audit-1400.png"
        res = open_in_chromium(work / "audit" / "audit.html", work / "b", shot, width=1400,
                               height=2400)  # fmt: skip
        lay = res["layout"]
        for e in res["errors"]:
            print("browser:", e)
        for o in lay["overlaps"]:
            print("overlap:", o)
        print(
            f"{shot}: page {lay['page']} px in a {lay['viewport']} px window, "
            f"{len(lay['past'])} element(s) past its edge, {len(lay['scrolls'])} table(s) "
            f"scrolling, {len(lay['overlaps'])} text overlap(s), {res['n_svg']} SVG, "
            f"{len(res['leaving'])} request(s) leaving, {len(res['errors'])} error(s); "
            f"{shot.stat().st_size // 1024} KiB"
        )


if __name__ == "__main__":
    main()
