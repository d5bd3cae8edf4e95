"""The shared touch-up loop on a standalone simulated cell: captures, time, pin accuracy.

Runs every planned pose of a scenario (the standard cell, ``--per-target`` poses
per target) through :func:`pipeline.live.loop.touch_up` on
:class:`pipeline.sim.cell_adapter.SimCell` (nothing recorded), probing the
Jacobian at the first touch-up of each target, in three set-ups:

- ``paper``: the simulated controller's detector, the probed Jacobian fixed
  (what the simulator's recordings do);
- ``vtcal``: vtcal's own detector, the probed Jacobian fixed;
- ``vtcal+broyden``: vtcal's detector, the Jacobian updated from the loop's
  steps and carried from one touch-up of a target to the next.

Printed per set-up: touch-ups converged, loop captures (iterations) and all
captures per converged touch-up (probing excluded, repeats included), probing
captures, simulated robot time and wall time per touch-up, and the true pin's
miss of the target at the converged poses (RMS, max; mm).

    python benchmarks/bench_touchup_loop.py [--seed 7] [--per-target 6]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import tomllib
from pathlib import Path

import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.live.detector import vtcal_detector
from pipeline.live.loop import CaptureInfo, Detector, estimate_jacobian, touch_up
from pipeline.live.protocols import Frame
from pipeline.sim.cell_adapter import SimCell
from pipeline.sim.scenario import scenario_from_dict

REPO = Path(__file__).resolve().parent.parent


def run(setup: str, seed: int, per_target: int) -> dict[str, float]:
    raw = tomllib.loads((REPO / "datasets" / "scenarios" / "standard.toml").read_text())
    raw.setdefault("poses", {})["per_target"] = per_target
    sc = scenario_from_dict(raw, where="standard", base_dir=str(REPO))
    cell = SimCell.from_scenario(sc, seed)
    cfg = cell.loop_config()
    detect: Detector
    if setup == "paper":
        detect = cell.detector()
    else:
        detect = vtcal_detector(cell.goal.polarity, size_px=cell.goal.s0)
    if setup.endswith("broyden"):
        cfg = dataclasses.replace(cfg, update_jacobian=True)
    kinds: list[str] = []

    def on_capture(frame: Frame, info: CaptureInfo) -> None:
        kinds.append(info.kind)

    jac: dict[int, F64] = {}
    sess = cell.sess
    arm = cell.robot.arm
    conv = 0
    per_conv: list[int] = []
    iters: list[int] = []
    miss: list[float] = []
    t_sim = arm.t
    t0 = time.perf_counter()
    for i, (tid, q) in enumerate(cell.plan):
        cell.camera.target = sess.cell.targets[tid]
        cell.robot.move_joints(q, 1.0)
        if tid not in jac:
            J = estimate_jacobian(cell.robot, cell.camera, detect, on_capture, cell.goal, cfg, i)
            if J is None:
                continue
            jac[tid] = J
        res = touch_up(cell.robot, cell.camera, detect, on_capture, cell.goal, cfg, jac[tid], i)
        if res.jacobian is not None and cfg.update_jacobian:
            jac[tid] = res.jacobian
        if res.converged:
            conv += 1
            per_conv.append(len(res.captures))
            iters.append(res.iterations)
            pin = sess.true_pin(res.joints.positions)
            miss.append(float(np.linalg.norm(pin - sess.cell.targets[tid].centre)))
    wall = time.perf_counter() - t0
    n = len(cell.plan)
    m = np.array(miss) * 1e3
    return {
        "n": n,
        "converged": conv,
        "iterations": float(np.mean(iters)),
        "captures": float(np.mean(per_conv)),
        "probes": float(kinds.count("probe")),
        "robot_s": (arm.t - t_sim) / 1e9 / n,
        "wall_s": wall / n,
        "miss_rms": float(np.sqrt(np.mean(m**2))),
        "miss_max": float(m.max()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--per-target", type=int, default=6)
    args = ap.parse_args()
    print(
        f"{'set-up':<14} {'converged':>9} {'iters':>6} {'captures':>8} {'probes':>6}"
        f" {'robot s':>8} {'wall s':>7} {'miss RMS':>8} {'miss max':>8}"
    )
    for setup in ("paper", "vtcal", "vtcal+broyden"):
        r = run(setup, args.seed, args.per_target)
        print(
            f"{setup:<14} {r['converged']:>4d}/{r['n']:<4d} {r['iterations']:6.2f}"
            f" {r['captures']:8.2f} {r['probes']:6.0f} {r['robot_s']:8.2f} {r['wall_s']:7.3f}"
            f" {r['miss_rms']:8.4f} {r['miss_max']:8.4f}",
            flush=True,
        )
    print(
        "per touch-up; captures = loop + repeat captures of a converged touch-up (probing"
        " excluded); robot s = simulated cell time incl. probing; miss = true pin - target, mm"
    )


if __name__ == "__main__":
    main()
