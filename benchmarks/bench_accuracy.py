"""End-to-end calibration accuracy against simulated truth.

For each robot family and pose count: simulate a recording with a calibration bar
(``vtcal simulate``), run the whole pipeline on it (``vtcal run``), and measure the
shipped ``calibrated.urdf`` the way ``spec/outputs.md`` does: virtual-pin
positions over poses spread through the volume the touch-ups covered, registered to
the true ones by a similarity (shape) and by a rigid motion (absolute). Printed
beside them: the nominal robot (before), the covariance-predicted error and the
cross-validated (held-out) error of the shipped model.

    python benchmarks/bench_accuracy.py            # lrmate and ur5e at 72 and 36, iiwa7 at 36
    python benchmarks/bench_accuracy.py --quick    # lrmate 72 only
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from pipeline.accuracy.evaluate import judge_run
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.sim.scenario import scenario_from_dict
from pipeline.sim.simulator import write_recording

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = {"lrmate": "standard.toml", "ur5e": "ur.toml", "iiwa7": "iiwa.toml"}


def one_case(robot: str, per_target: int, seed: int, work: Path) -> dict[str, float]:
    raw = tomllib.loads((REPO / "datasets" / "scenarios" / SCENARIOS[robot]).read_text())
    raw.setdefault("poses", {})["per_target"] = per_target
    sc = scenario_from_dict(raw, where=f"{robot}-{per_target}", base_dir=str(REPO))
    rec = work / f"{robot}_{per_target}_{seed}.mcap"
    t0 = time.perf_counter()
    truth = write_recording(sc, seed, rec)
    t_sim = time.perf_counter() - t0
    out = work / rec.stem
    t0 = time.perf_counter()
    run_pipeline(rec, out, RunConfig(report=False), until="crossval")
    t_run = time.perf_counter() - t0
    judged = judge_run(out, truth, 500, seed)
    summary, best, model_summary = judged["summary"], judged["best"], judged["model_summary"]
    after, before = judged["after"], judged["before"]
    cv = summary.get("crossval", {}).get("models", {}).get(best, {})
    return {
        "n_used": float(model_summary.get("n_used", np.nan)),
        "before_rms": before["shape_rms_m"] * 1e3,
        "shape_rms": after["shape_rms_m"] * 1e3,
        "shape_max": after["shape_max_m"] * 1e3,
        "abs_rms": after["abs_rms_m"] * 1e3,
        "abs_max": after["abs_max_m"] * 1e3,
        "pred_rms": float(model_summary.get("predicted_shape_rms_mm", np.nan)),
        "cv_rms": float(cv.get("kfold_rms_mm", np.nan)),
        "t_sim": t_sim,
        "t_run": t_run,
        "model": best,  # type: ignore[dict-item]
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    cases = (
        [("lrmate", 24)]
        if args.quick
        else [("lrmate", 24), ("lrmate", 12), ("ur5e", 24), ("ur5e", 12), ("iiwa7", 12)]
    )
    print(
        f"{'robot':<7} {'touch-ups':>9} {'model':<8} {'nominal':>8} {'shape RMS':>9} {'shape max':>9}"
        f" {'abs RMS':>8} {'abs max':>8} {'abs/shape':>9} {'predicted':>9} {'held-out':>8}"
        f" {'sim s':>6} {'run s':>6}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for robot, per_target in cases:
            r = one_case(robot, per_target, args.seed, Path(tmp))
            print(
                f"{robot:<7} {int(r['n_used']):>9d} {r['model']!s:<8} {r['before_rms']:8.3f}"
                f" {r['shape_rms']:9.4f} {r['shape_max']:9.4f} {r['abs_rms']:8.4f}"
                f" {r['abs_max']:8.4f} {r['abs_rms'] / r['shape_rms']:9.2f} {r['pred_rms']:9.4f}"
                f" {r['cv_rms']:8.4f} {r['t_sim']:6.1f} {r['t_run']:6.1f}",
                flush=True,
            )
    print(
        "mm; nominal = nominal robot with the true pin (shape RMS); targets: 72 touch-ups"
        " shape RMS < 0.05, max < 0.15, abs RMS within 25 % of shape"
    )
    sys.exit(0)


if __name__ == "__main__":
    main()
