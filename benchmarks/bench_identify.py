"""Identification benchmark: time and accuracy, measured in one run, printed side by side.

    python benchmarks/bench_identify.py [--seeds 5] [--robot lrmate]

Synthetic touch-ups of a true robot (nominal URDF + per-joint origin deviations
of the simulator's magnitudes: 1 mm, 3 mrad, 1.5 mrad zero offsets), 3 targets,
the true pin exactly on the target up to a contact noise of 0.01 mm RMS (3D)
and 1e-6 rad encoder noise. Accuracy as ``spec/outputs.md`` measures
it (pipeline.accuracy.evaluate.pin_accuracy over poses spread through the touched
volume). Prints:

1. time of ``identify`` on 36 touch-ups with the full model (warm: the
   per-robot structural identifiability is cached; and cold), next to
   pybotics' least-squares calibration (MDH, numeric Jacobian) on the same
   touch-ups -- pybotics cannot estimate unknown targets, so it is handed the
   TRUE target centres (a laser tracker's view), which favours it;
2. accuracy (shape / absolute, RMS / max) per model with 36 and 72 touch-ups,
   with and without a known distance, next to the nominal robot's, and the
   covariance-predicted error next to the measured one (their ratio);
3. the no-modelling-loss check: exact touch-ups, every complete model.

With ``--run RUN_DIR --recording REC.mcap`` it instead judges a finished
``vtcal run`` of a simulated recording against its truth file (end to end:
detection, touch-up extraction, outliers, identification), every model.

pybotics is a test-only peer (its metadata pins numpy<2 although it runs on
numpy 2): ``pip install --no-deps pybotics attrs``. Without it its row says
unavailable.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.accuracy.evaluate import (  # noqa: E402
    perturbed_chain,
    pin_accuracy,
    pin_positions,
    random_deviations,
    registered_errors,
    synthetic_touchups,
    workspace_poses,
)
from pipeline.kinematics import load_chain  # noqa: E402
from pipeline.models.mdh import MDHModel  # noqa: E402
from pipeline.robots import builtin_urdf  # noqa: E402
from pipeline.stages.identify import stage as ident  # noqa: E402

PIN = np.array([0.0167, -0.0101, 0.2524])
CENTRES = {
    "lrmate": np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32]),
    "ur5e": np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2]),
    "iiwa7": np.full(7, 0.3),
}


def case(robot: str, seed: int, per_target: int, noise: bool = True):
    urdf = builtin_urdf(robot)
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    table, targets = synthetic_touchups(
        true,
        PIN,
        3,
        per_target,
        rng,
        noise_q_rad=1e-6 if noise else 0.0,
        noise_pin_m=1e-5 / np.sqrt(3) if noise else 0.0,
        q_centre=CENTRES[robot],
    )
    qw = workspace_poses(table[nominal.joint_names].to_numpy(), 500, np.random.default_rng(99))
    return urdf, nominal, true, table, targets, qw


def time_min(fn, n: int = 15) -> tuple[float, float]:
    """Smallest wall and CPU (process) time of ``n`` calls, seconds."""
    wall = cpu = np.inf
    for _ in range(n):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - t)
        cpu = min(cpu, time.process_time() - c)
    return wall, cpu


def pybotics_calibrate(nominal, table, targets, qw, true):
    """pybotics MDH least squares on the same touch-ups with the true target centres."""
    try:
        from pybotics.optimization import OptimizationHandler, optimize_accuracy
        from pybotics.robot import Robot
        from scipy.optimize import least_squares
    except Exception as exc:  # noqa: BLE001
        return None, f"unavailable ({type(exc).__name__}: {exc})"
    m = MDHModel(nominal)
    if np.any(np.abs(m.E - np.eye(4)) > 1e-12) or np.any(m.nom[:, 1] != 0):
        return None, "unavailable (robot needs a non-MDH constant)"
    params = m.nom[:, [0, 2, 3, 4]]  # alpha, a, theta, d
    robot = Robot.from_parameters(params)
    robot.world_frame = m.B
    T_tool = m.T_n_flange.copy()
    T_tool[:3, 3] = T_tool[:3, :3] @ PIN + T_tool[:3, 3]
    robot.tool.matrix = T_tool
    q = table[nominal.joint_names].to_numpy()
    pos = targets[table["target_id"].to_numpy()]
    handler = OptimizationHandler(
        robot=robot,
        kinematic_chain_mask=[True] * robot.kinematic_chain.num_parameters,
        tool_mask=[True, True, True, False, False, False],
    )
    x0 = handler.generate_optimization_vector()

    def run():
        return least_squares(
            fun=optimize_accuracy, x0=x0, args=(handler, q, pos), method="trf", max_nfev=200
        )

    t = time.perf_counter()
    res = run()
    seconds = time.perf_counter() - t
    handler.apply_optimization_vector(res.x)
    pm = np.array([handler.robot.fk(qi)[:3, 3] for qi in qw])
    pt = pin_positions(true, PIN, qw)
    es = registered_errors(pm, pt, scale=True)
    ea = registered_errors(pm, pt, scale=False)
    acc = {
        "shape_rms_m": float(np.sqrt(np.mean(es**2))),
        "shape_max_m": float(es.max()),
        "abs_rms_m": float(np.sqrt(np.mean(ea**2))),
        "abs_max_m": float(ea.max()),
    }
    return (seconds, acc, int(res.nfev)), ""


def fmt(acc) -> str:
    return (
        f"shape {acc['shape_rms_m'] * 1e3:7.4f} / {acc['shape_max_m'] * 1e3:7.4f}   "
        f"abs {acc['abs_rms_m'] * 1e3:7.4f} / {acc['abs_max_m'] * 1e3:7.4f}"
    )


def evaluate_run(run_dir: Path, recording: Path) -> None:
    """Accuracy of a finished ``vtcal run`` against the simulator's truth, every model."""
    import json

    import pandas as pd

    from pipeline.io.known_distances import parse_distances

    t = json.loads(Path(str(recording) + ".truth.json").read_text())
    base, fl = t["base_link"], t["flange_link"]
    true = load_chain(t["true_urdf"], base, fl)
    pin_true = np.array(t["p_vt_flange"])
    nominal = load_chain(t["nominal_urdf"], base, fl)
    inl = pd.read_parquet(run_dir / "inliers.parquet")
    q = inl[inl["inlier"]][true.joint_names].to_numpy()
    qw = workspace_poses(q, 500, np.random.default_rng(0))
    print(
        f"== run {run_dir} ({int(inl['inlier'].sum())} inlier touch-ups of {len(inl)}) "
        "vs truth, mm: shape RMS / max, abs RMS / max"
    )
    print(f"nominal    {fmt(pin_accuracy(nominal, pin_true, true, pin_true, qw))}")
    urdf = (run_dir / "calibrated.urdf").read_text()
    cal = load_chain(urdf, base, fl)
    pin = load_chain(urdf, base, "virtual_pin").joints[-1].T_parent_joint[:3, 3]
    print(f"shipped    {fmt(pin_accuracy(cal, pin, true, pin_true, qw))}")
    dist = parse_distances(t["metadata"].get("known_distances", ""))
    res = ident.identify(
        inl, t["nominal_urdf"], base, fl, ident.IdentifyConfig(model="all", distances=dist)
    )
    assert isinstance(res, dict)
    for name, r in res.items():
        a = pin_accuracy(r.chain, r.p_flange_pin, true, pin_true, qw)
        pred = r.summary["predicted_shape_rms_mm"]
        print(
            f"{name:9s}  {fmt(a)}   predicted shape RMS {pred:.4f}  "
            f"measured/predicted {a['shape_rms_m'] * 1e3 / pred:.2f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--robot", default="lrmate", choices=sorted(CENTRES))
    ap.add_argument("--run", type=Path, help="evaluate a finished vtcal run folder instead")
    ap.add_argument("--recording", type=Path, help="the simulated recording of --run")
    args = ap.parse_args()
    if args.run is not None:
        evaluate_run(args.run, args.recording)
        return
    robot = args.robot

    # 1. time, 36 touch-ups, full model, next to pybotics
    print(f"== 1. time: 36 touch-ups (3 targets x 12), {robot}, model full")
    urdf, nominal, true, table, targets, qw = case(robot, 0, 12)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    cfg = ident.IdentifyConfig(model="full", distances=[(0, 2, d02)])
    ident._structure.cache_clear()
    t = time.perf_counter()
    r = ident.identify(table, urdf, "base_link", "flange", cfg)
    cold = time.perf_counter() - t
    warm, warm_cpu = time_min(lambda: ident.identify(table, urdf, "base_link", "flange", cfg))
    acc = pin_accuracy(r.chain, r.p_flange_pin, true, PIN, qw)
    print(
        f"vtcal identify  warm {warm * 1e3:7.1f} ms (CPU {warm_cpu * 1e3:.1f} ms)  cold "
        f"{cold * 1e3:7.1f} ms (structure per robot, cached)  nfev "
        f"{r.summary['solver']['nfev']}  [mm RMS/max] {fmt(acc)}"
    )
    print(
        f"load average now: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores "
        "(wall time inflates under load; CPU time does not)"
    )
    pb, why = pybotics_calibrate(nominal, table, targets, qw, true)
    if pb is None:
        print(f"pybotics        {why}")
    else:
        seconds, pacc, nfev = pb
        print(
            f"pybotics lsq    {seconds * 1e3:7.1f} ms  (given TRUE targets; MDH, numeric J)"
            f"  nfev {nfev}  [mm RMS/max] {fmt(pacc)}"
        )
        print(f"time ratio pybotics / vtcal (warm): {seconds / warm:.1f}x")
    print(
        f"target < 50 ms: wall {'met' if warm < 0.05 else 'NOT met'} ({warm * 1e3:.1f} ms), "
        f"CPU {'met' if warm_cpu < 0.05 else 'NOT met'} ({warm_cpu * 1e3:.1f} ms)"
    )

    # 2. accuracy over seeds
    print(f"\n== 2. accuracy over {args.seeds} seeds (mm, mean over seeds; max = worst seed)")
    print(
        "touch-ups  model    distance  shape RMS  shape max  abs RMS  abs max  "
        "predicted RMS  measured/predicted"
    )
    for per in (12, 24):
        rows: dict[tuple[str, bool], list] = {}
        nom_rows = []
        for seed in range(args.seeds):
            urdf, nominal, true, table, targets, qw = case(robot, 100 + seed, per)
            nom_rows.append(pin_accuracy(nominal, PIN, true, PIN, qw))
            d02 = float(np.linalg.norm(targets[0] - targets[2]))
            for with_d in (True, False):
                res = ident.identify(
                    table,
                    urdf,
                    "base_link",
                    "flange",
                    ident.IdentifyConfig(model="all", distances=[(0, 2, d02)] if with_d else []),
                )
                assert isinstance(res, dict)
                for name, rr in res.items():
                    a = pin_accuracy(rr.chain, rr.p_flange_pin, true, PIN, qw)
                    a["pred"] = rr.summary["predicted_shape_rms_mm"] * 1e-3
                    rows.setdefault((name, with_d), []).append(a)
        n = 3 * per
        nm = {k: np.mean([a[k] for a in nom_rows]) for k in nom_rows[0]}
        print(
            f"{n:9d}  nominal  -         {nm['shape_rms_m'] * 1e3:9.4f}  "
            f"{nm['shape_max_m'] * 1e3:9.4f}  {nm['abs_rms_m'] * 1e3:7.4f}  "
            f"{nm['abs_max_m'] * 1e3:7.4f}"
        )
        for (name, with_d), accs in sorted(rows.items()):
            sr = np.mean([a["shape_rms_m"] for a in accs]) * 1e3
            sm = np.max([a["shape_max_m"] for a in accs]) * 1e3
            ar = np.mean([a["abs_rms_m"] for a in accs]) * 1e3
            am = np.max([a["abs_max_m"] for a in accs]) * 1e3
            pr = np.mean([a["pred"] for a in accs]) * 1e3
            print(
                f"{n:9d}  {name:7s}  {'yes' if with_d else 'no ':8s}  {sr:9.4f}  {sm:9.4f}  "
                f"{ar:7.4f}  {am:7.4f}  {pr:13.4f}  {sr / pr:18.2f}"
            )
    print(
        "(without a distance the scale is held at nominal: absolute figures then carry the "
        "scale error; shape is what touch-ups deliver)"
    )
    print(
        "(the covariance sees the random noise only; a ratio near 1 says the fit absorbs no "
        "systematic error on this synthetic data)"
    )

    # 3. no modelling loss
    print("\n== 3. no modelling loss: exact touch-ups (36), known distance; max pin error, mm")
    for rb in ("lrmate", "ur5e", "iiwa7"):
        urdf, nominal, true, table, targets, qw = case(
            rb, 7, 12 if rb != "iiwa7" else 14, noise=False
        )
        d02 = float(np.linalg.norm(targets[0] - targets[2]))
        out = []
        for name in ("full", "mdh", "poe"):
            rr = ident.identify(
                table,
                urdf,
                "base_link",
                "flange",
                ident.IdentifyConfig(model=name, distances=[(0, 2, d02)]),
            )
            a = pin_accuracy(rr.chain, rr.p_flange_pin, true, PIN, qw)
            out.append(f"{name} shape {a['shape_max_m'] * 1e3:.1e} abs {a['abs_max_m'] * 1e3:.1e}")
        print(f"{rb:7s} " + "   ".join(out))


if __name__ == "__main__":
    main()
