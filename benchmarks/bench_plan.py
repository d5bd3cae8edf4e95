"""Pose-planner benchmark: planned vs random poses through the real identification.

    python benchmarks/bench_plan.py [--seeds 5] [--reps 4] [--robots lrmate,ur5e]

For each robot (the simulator's standard cell: ``datasets/targets/ROBOT_cell.csv``,
pin ~(0.03, 0, 0.25) m in the flange frame) and seed:

* ``vtcal plan``'s stage (:func:`pipeline.plan.planner.plan_poses`) picks 36
  poses out of ~2,000 candidates (criterion O1, model full);
* a true robot (uniform per-joint origin deviations of the simulator's size:
  0.5 mm, 1.5 mrad, 1 mrad zero offsets) and a true pin 2 mm off the assumed one
  are touched up at the planned poses, at 36 and at 72 poses drawn at random from
  the same usable candidates (:mod:`pipeline.plan.check`): contact miss 0.01 mm
  per axis, encoder noise 1e-6 rad; each set ``--reps`` times with fresh noise;
* every table goes through ``pipeline.stages.identify.stage.identify`` (model full, no
  known distance) and is scored by ``pipeline.accuracy.evaluate.pin_accuracy`` (shape RMS)
  over the plan's evaluation poses (spread through the candidates' joint box);
  a seed's figure is the RMS over its repetitions.

Prints per robot: the per-seed shape RMS of each set, the medians over seeds and
their ratios (planned / random 36 must be <= 0.70; planned 36 / random 72 <= 1),
the plan's predicted error against the measured one (RMS over seeds and
repetitions; within 30 %), and the time to choose 36 poses from 2,000
candidates for each criterion (must be < 10 s).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.kinematics.chain import load_chain  # noqa: E402
from pipeline.plan.candidates import (  # noqa: E402
    CandidateConfig,
    generate_candidates,
    working_radius,
)
from pipeline.plan.check import calibrate_and_score, touchups_at, true_world  # noqa: E402
from pipeline.plan.design import build_design  # noqa: E402
from pipeline.plan.planner import PlanConfig, plan_poses  # noqa: E402
from pipeline.plan.select import CRITERIA, select_poses  # noqa: E402
from pipeline.plan.targets import read_targets  # noqa: E402
from pipeline.robots import load_urdf  # noqa: E402

PIN = (0.03, 0.0, 0.25)
NOISE_PIN_M = 1e-5
NOISE_Q_RAD = 1e-6


def measure(
    urdf: str, robot: str, seed: int, reps: int, n_poses: int
) -> dict[str, float | list[float]]:
    tg = read_targets(ROOT / f"datasets/targets/{robot}_cell.csv")
    res = plan_poses(urdf, tg, PlanConfig(n_poses=n_poses, p_flange_pin=PIN, seed=seed))
    cs, d = res.candidates, res.design
    pos = {c: i for i, c in enumerate(cs.accepted["candidate_id"].tolist())}
    planned = np.array([pos[c] for c in res.table["candidate_id"]])
    rng = np.random.default_rng(1000 + seed)
    chain_t, pin_t, tg_t = true_world(d.model.nominal, PIN, tg.centres, rng)
    sets = {
        "planned": planned,
        "random": rng.choice(len(d), n_poses, replace=False),
        "random2x": rng.choice(len(d), 2 * n_poses, replace=False),
    }
    out: dict[str, float | list[float]] = {}
    sigma = res.summary["sigma_pin_mm"] * 1e-3
    for name, idx in sets.items():
        errs = []
        for _ in range(reps):
            table = touchups_at(
                chain_t,
                pin_t,
                tg_t,
                cs.q[idx],
                cs.target_index[idx],
                rng,
                noise_pin_m=NOISE_PIN_M,
                noise_q_rad=NOISE_Q_RAD,
            )
            errs.append(calibrate_and_score(table, urdf, chain_t, pin_t, res.eval_q)["shape_rms_m"])
        out[name] = float(np.sqrt(np.mean(np.square(errs))))
        out[name + "_pred"] = d.predicted_error(idx, sigma, res.eval_q)["shape_rms_m"]
    out["plan_pred"] = res.summary["predicted_shape_rms_mm"] * 1e-3
    out["select_s"] = res.summary["seconds"]["selection"]
    out["usable"] = float(res.summary["candidates"]["usable"])
    return out


def timing(urdf: str, robot: str, n_cand: int = 2000, n_poses: int = 36) -> dict[str, float]:
    """Seconds to choose ``n_poses`` of exactly ``n_cand`` usable candidates, per criterion."""
    tg = read_targets(ROOT / f"datasets/targets/{robot}_cell.csv")
    chain = load_chain(urdf, "base_link", "flange")
    cs = generate_candidates(
        chain, tg, CandidateConfig(n_candidates=int(n_cand * 1.15), p_flange_pin=PIN)
    )
    q, tk = cs.q[:n_cand], cs.target_index[:n_cand]
    t0 = time.perf_counter()
    d = build_design(chain, "full", q, tk, len(tg), PIN, working_radius(tg.centres))
    out = {"design": time.perf_counter() - t0, "n": float(len(q))}
    for c in CRITERIA:
        t0 = time.perf_counter()
        select_poses(d, n_poses, c)
        out[c] = time.perf_counter() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=4)
    ap.add_argument("--poses", type=int, default=36)
    ap.add_argument("--robots", default="lrmate,ur5e")
    args = ap.parse_args()
    t_all = time.perf_counter()
    print(
        f"bench_plan: {args.poses} planned poses (O1, model full) vs random from the same "
        f"candidates; {args.seeds} seeds x {args.reps} noise repetitions; contact noise "
        f"{NOISE_PIN_M * 1e3:.3f} mm/axis, encoder {NOISE_Q_RAD:g} rad; shape RMS in mm"
    )
    for robot in args.robots.split(","):
        urdf = load_urdf(robot)
        rows = [measure(urdf, robot, s, args.reps, args.poses) for s in range(args.seeds)]
        print(f"\n[{robot}]  seed  planned{args.poses}  random{args.poses}  random{2 * args.poses}"
              "   (predicted: planned / random / random2x)")  # fmt: skip
        for s, r in enumerate(rows):
            print(
                f"          {s:4d}  {float(r['planned']) * 1e3:9.4f}  {float(r['random']) * 1e3:8.4f}"
                f"  {float(r['random2x']) * 1e3:8.4f}   ({float(r['planned_pred']) * 1e3:.4f} / "
                f"{float(r['random_pred']) * 1e3:.4f} / {float(r['random2x_pred']) * 1e3:.4f})"
            )
        med = {
            k: float(np.median([float(r[k]) for r in rows]))
            for k in ("planned", "random", "random2x")
        }
        print(
            f"  median shape RMS: planned {med['planned'] * 1e3:.4f} mm, random {med['random'] * 1e3:.4f} mm, "
            f"random x2 {med['random2x'] * 1e3:.4f} mm"
        )
        ratio = med["planned"] / med["random"]
        print(
            f"  planned / random (same count) = {ratio:.3f} -> {100 * (1 - ratio):.0f} % lower "
            f"[{'PASS' if ratio <= 0.70 else 'FAIL'} (>= 30 % lower)]"
        )
        r2 = med["planned"] / med["random2x"]
        print(
            f"  planned {args.poses} / random {2 * args.poses} = {r2:.3f} "
            f"[{'PASS' if r2 <= 1.0 else 'FAIL'} (<= 1)]"
        )
        meas = np.sqrt(np.mean([float(r["planned"]) ** 2 for r in rows]))
        pred = np.sqrt(np.mean([float(r["plan_pred"]) ** 2 for r in rows]))
        rp = meas / pred
        print(
            f"  plan's predicted shape RMS {pred * 1e3:.4f} mm vs measured {meas * 1e3:.4f} mm "
            f"(RMS over seeds): measured / predicted = {rp:.3f} "
            f"[{'PASS' if abs(rp - 1) <= 0.30 else 'FAIL'} (within 30 %)]"
        )
        print(
            "  selection time in the planner: "
            + ", ".join(
                f"{float(r['select_s']):.2f} s ({int(float(r['usable']))} usable)" for r in rows
            )
        )
        t = timing(urdf, robot)
        print(
            f"  choose {args.poses} of {int(t['n'])} candidates: design {t['design']:.2f} s; "
            + ", ".join(f"{c} {t[c]:.2f} s" for c in CRITERIA)
            + f" [{'PASS' if max(t[c] for c in CRITERIA) < 10 else 'FAIL'} (< 10 s)]"
        )
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
