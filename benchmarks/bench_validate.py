"""vtcal validate on a second recording of the same simulated cell.

Two recordings of the standard LR Mate-like cell with the same seed (hence the
same true robot, camera and targets): the first with the scenario's own poses,
the second with 36 poses from ``vtcal plan``. ``vtcal run`` calibrates the first;
``vtcal validate`` judges its ``calibrated.urdf`` on the second, next to the
simulator's true robot (the touch-up noise floor) and the nominal robot with a
refitted pin::

    python benchmarks/bench_validate.py            # seed 1
    python benchmarks/bench_validate.py --seed 2
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from pipeline.cli import main as vtcal_main

REPO = Path(__file__).resolve().parent.parent
SCENARIO = REPO / "datasets" / "scenarios" / "standard.toml"
TARGETS = REPO / "datasets" / "targets" / "lrmate_cell.csv"
PIN = "0.047,0.002,0.251"  # the standard cell's virtual pin (README, vtcal plan)


def vtcal(*args: str) -> int:
    try:
        vtcal_main(list(args))
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def timed(label: str, *args: str) -> int:
    t0 = time.perf_counter()
    code = vtcal(*args)
    print(f"[{label}: exit {code}, {time.perf_counter() - t0:.1f} s]")
    return code


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    seed = str(args.seed)
    with tempfile.TemporaryDirectory(prefix="bench_validate_") as tmp:
        w = Path(tmp)
        timed("simulate rec1", "simulate", "--scenario", str(SCENARIO), "--seed", seed,
              "--out", str(w / "rec1.mcap"), "--quiet")  # fmt: skip
        timed("plan", "plan", "--urdf", "lrmate", "--targets", str(TARGETS), "--poses", "36",
              "--pin", PIN, "--out", str(w / "plan.parquet"))  # fmt: skip
        timed("simulate rec2", "simulate", "--scenario", str(SCENARIO), "--seed", seed,
              "--plan", str(w / "plan.parquet"), "--out", str(w / "rec2.mcap"), "--quiet")  # fmt: skip
        timed("run rec1", "run", str(w / "rec1.mcap"), "--out", str(w / "run1"), "-q",
              "--no-report")  # fmt: skip
        truth = json.loads((w / "rec2.mcap.truth.json").read_text())
        (w / "true.urdf").write_text(truth["true_urdf_with_pin"])
        rows = {}
        for name, urdf in (
            ("calibrated", w / "run1" / "calibrated.urdf"),
            ("true", w / "true.urdf"),
        ):
            out = w / f"val_{name}"
            timed(f"validate {name}", "validate", str(urdf), str(w / "rec2.mcap"), "--out",
                  str(out), "-q")  # fmt: skip
            rows[name] = json.loads((out / "validate.json").read_text())
    print(f"\nseed {seed}: calibrated on rec1, judged on rec2 (consistency RMS / max, mm)")
    cal, true = rows["calibrated"], rows["true"]
    for r in cal["robots"]:
        print(f"  {r['label']:<28} {r['consistency_mm']:.4f} / {r['max_mm']:.4f}")
    t = true["robots"][0]
    print(f"  {'true robot (noise floor)':<28} {t['consistency_mm']:.4f} / {t['max_mm']:.4f}")
    print(f"  {cal['n_touchups']} touch-ups of {len(cal['targets'])} targets judged")
    print(f"  {cal['verdict']['line']}")


if __name__ == "__main__":
    main()
