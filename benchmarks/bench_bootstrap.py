"""Benchmark: the identification covariance checked by a bootstrap over touch-ups.

For each run folder given (``vtcal run`` output): its touch-ups (``inliers.parquet``,
the inliers) are resampled with replacement ``--draws`` times (each target keeps at
least one touch-up; the known distances and the model are the run's shipped ones),
each resample refitted, and its virtual pin predicted at the same workspace poses
(:func:`pipeline.accuracy.evaluate.workspace_poses`, the covered joint ranges). The scatter of
those predictions about their mean, after the same rigid / similarity registration as
the accuracy figures, is the bootstrap's error; the covariance's prediction is
identify's ``predicted_absolute`` / ``predicted_shape`` **without** the pin offset of
(P1) (:func:`pipeline.estimation.uncertainty.with_pin_offset`: a constant offset no
resample shows), recomputed here from the full fit. Prints per run the two and
their ratio (bootstrap / covariance; 1 when the covariance holds the touch-ups'
scatter, with a Monte-Carlo error of about ``1/sqrt(2 draws)``).

    python benchmarks/bench_bootstrap.py RUN_DIR [RUN_DIR ...] [--draws 100] [--seed 0]
    python benchmarks/bench_bootstrap.py --simulate 3 [--draws 100]

``--simulate SEED``: the check of the check, where the truth is known. An LR
Mate-like robot with random link errors, 3 targets x 12 touch-ups with a known
distance, touch-up noise in the flange frame (5, 5, 40 um: a touch-up is least
precise along the view) as the corrections ``d``; the same poses with 40 noise
draws give the true error of a fit (its pins against the true robot's, registered),
which the covariance should predict and the bootstrap of one draw estimates.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.accuracy.evaluate import registered_errors, workspace_poses
from pipeline.audit.fit import fit_table
from pipeline.audit.identity import load_item
from pipeline.errors import VtcalError


def resample(table: pd.DataFrame, rng: np.random.Generator) -> pd.DataFrame:
    """The touch-ups drawn with replacement within each target, renumbered."""
    parts = []
    for _, g in table.groupby("target_id", sort=False):
        parts.append(g.iloc[rng.integers(0, len(g), len(g))])
    out = pd.concat(parts, ignore_index=True)
    out["touchup_id"] = np.arange(len(out))
    return out


def pins(res, q: np.ndarray) -> np.ndarray:
    """The fitted model's virtual pin at joint vectors ``q`` (W, n), base frame (m)."""
    p, _, _ = res.error_model.pin_and_jacobian(res.x, q, res.p_flange_pin, jac=False)
    return np.asarray(p)


def one_run(run: Path, draws: int, seed: int) -> dict[str, float]:
    item = load_item(run, robot_id="bootstrap")
    summary = json.loads((run / "identify.json").read_text())
    model = str(summary.get("best_model") or summary.get("model"))
    table = item.table[item.table["inlier"].astype(bool)] if "inlier" in item.table else item.table
    joints = [c for c in table.columns if c.startswith("joint_")]
    rng = np.random.default_rng(seed)
    q = workspace_poses(table[joints].to_numpy(), 200, rng)
    full = fit_table(table, item.urdf, item.base_link, item.flange_link, model, item.distances)
    p_full = pins(full, q)
    P = []
    t0 = time.perf_counter()
    for _ in range(draws):
        try:
            res = fit_table(
                resample(table, rng), item.urdf, item.base_link, item.flange_link, model,
                item.distances,
            )  # fmt: skip
        except VtcalError:
            continue
        P.append(pins(res, q))
    P_arr = np.array(P)
    mean = P_arr.mean(axis=0)
    boot = {
        kind: float(
            np.sqrt(np.mean([np.mean(registered_errors(p, mean, scale=sc) ** 2) for p in P_arr]))
        )
        for kind, sc in (("absolute", False), ("shape", True))
    }
    cov = full_covariance_prediction(full, q)
    return {
        "run": run.name,
        "model": model,
        "draws": len(P),
        "seconds": time.perf_counter() - t0,
        "boot_abs_mm": boot["absolute"] * 1e3,
        "cov_abs_mm": cov["absolute"] * 1e3,
        "boot_shape_mm": boot["shape"] * 1e3,
        "cov_shape_mm": cov["shape"] * 1e3,
        "bias_full_vs_mean_mm": float(np.sqrt(np.mean(np.sum((p_full - mean) ** 2, axis=1)))) * 1e3,
    }


def full_covariance_prediction(res, q: np.ndarray) -> dict[str, float]:
    """RMS of the covariance-predicted errors at ``q`` (m), without (P1)."""
    from pipeline.estimation.region import predicted_over

    names = list(res.covariance_names or [])
    kept_names = [n for n in names if not n.startswith(("pin.", "target."))]
    pnames = list(res.error_model.param_names)
    kept = np.array([pnames.index(n) for n in kept_names], dtype=int)
    idx = [names.index(n) for n in kept_names] + [names.index(f"pin.{a}") for a in "xyz"]
    cov_e = np.asarray(res.covariance)[np.ix_(idx, idx)]
    pred, _ = predicted_over(res.error_model, res.x, res.p_flange_pin, kept, cov_e, q)
    return {k: float(np.sqrt(np.mean(v**2))) for k, v in pred.items()}


def simulate(seed: int, draws: int, model: str = "poe") -> dict[str, float]:
    """True error, covariance and bootstrap on a seeded simulated cell (module docstring)."""
    from pipeline.accuracy.evaluate import (
        perturbed_chain,
        pin_positions,
        random_deviations,
        synthetic_touchups,
    )
    from pipeline.kinematics.chain import load_chain
    from pipeline.robots import builtin_urdf

    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    pin = np.array([0.01, -0.02, 0.2])
    design, tg = synthetic_touchups(
        true, pin, 3, 12, rng, q_centre=[0.0, 0.3, -0.3, 0.0, -0.8, 0.0], spread_rad=0.6
    )
    dist = [(0, 2, float(np.linalg.norm(tg[0] - tg[2])))]
    sd = np.array([5e-6, 5e-6, 40e-6])
    joints = [c for c in design.columns if c.startswith("joint_")]
    q = workspace_poses(design[joints].to_numpy(), 200, rng)
    p_true = pin_positions(true, pin, q)

    def noisy() -> pd.DataFrame:
        t = design.copy()
        t[["dx_flange", "dy_flange", "dz_flange"]] = rng.normal(0.0, 1.0, (len(t), 3)) * sd
        return t

    truth_ms = {"absolute": [], "shape": []}
    cov_ms = {"absolute": [], "shape": []}
    first = None
    for _ in range(40):
        t = noisy()
        res = fit_table(t, urdf, "base_link", "flange", model, dist)
        first = first if first is not None else (t, res)
        p = pins(res, q)
        for kind, sc in (("absolute", False), ("shape", True)):
            truth_ms[kind].append(np.mean(registered_errors(p, p_true, scale=sc) ** 2))
        c = full_covariance_prediction(res, q)
        for kind in cov_ms:
            cov_ms[kind].append(c[kind] ** 2)
    t0, _ = first
    P = np.array(
        [
            pins(fit_table(resample(t0, rng), urdf, "base_link", "flange", model, dist), q)
            for _ in range(draws)
        ]
    )
    mean = P.mean(axis=0)
    out: dict[str, float] = {}
    for kind, sc in (("absolute", False), ("shape", True)):
        out[f"true_{kind}_mm"] = float(np.sqrt(np.mean(truth_ms[kind]))) * 1e3
        out[f"cov_{kind}_mm"] = float(np.sqrt(np.mean(cov_ms[kind]))) * 1e3
        out[f"boot_{kind}_mm"] = (
            float(np.sqrt(np.mean([np.mean(registered_errors(p, mean, scale=sc) ** 2) for p in P])))
            * 1e3
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--simulate", type=int, metavar="SEED", help="the seeded simulated cell")
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.simulate is not None:
        r = simulate(args.simulate, args.draws)
        for kind in ("absolute", "shape"):
            t, c, b = (r[f"{w}_{kind}_mm"] for w in ("true", "cov", "boot"))
            print(
                f"simulated cell, seed {args.simulate}, {kind}: true {t:.4f} mm (40 noise draws),"
                f" covariance {c:.4f} ({c / t:.2f}x true), bootstrap of one draw {b:.4f}"
                f" ({b / t:.2f}x true, {b / c:.2f}x the covariance)"
            )
    if not args.runs:
        return
    print(
        f"{'run':<16} {'model':<7} {'draws':>5} {'boot abs':>9} {'cov abs':>8} {'ratio':>6}"
        f" {'boot shp':>9} {'cov shp':>8} {'ratio':>6} {'s':>6}"
    )
    for run in args.runs:
        r = one_run(run, args.draws, args.seed)
        print(
            f"{r['run']:<16} {r['model']:<7} {r['draws']:>5d} {r['boot_abs_mm']:9.4f}"
            f" {r['cov_abs_mm']:8.4f} {r['boot_abs_mm'] / r['cov_abs_mm']:6.2f}"
            f" {r['boot_shape_mm']:9.4f} {r['cov_shape_mm']:8.4f}"
            f" {r['boot_shape_mm'] / r['cov_shape_mm']:6.2f} {r['seconds']:6.1f}",
            flush=True,
        )
    print(
        "mm RMS of the virtual pin over 200 workspace poses: boot = the resamples' scatter"
        " about their mean after a rigid (abs) / similarity (shp) registration; cov ="
        " identify's covariance-predicted error without (P1)'s pin offset; ratio = boot / cov"
    )


if __name__ == "__main__":
    main()
