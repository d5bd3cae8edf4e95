"""Measuring on a cell: robot time per touch-up and per calibration, where it
goes (travel, settle, servo, capture), captures per converged touch-up, and the accuracy of
the calibration each loop's recording gives.

One run of the standard cell (lrmate, 3 targets x 12 poses, seed 1 unless ``--seed``), the
scenario's own plan measured four ways:

1. ``vtcal measure --order travel`` in process (``sim:``): the poses in the order of
   shortest joint travel, the shared loop at its defaults (gain 1.0, the Jacobian probed
   once per target and updated from the loop's own steps by Broyden's rule, 3 captures at
   convergence), large moves at ``--speed 0.5``;
2. the same over TCP against ``vtcal cell-server`` in another process (a real socket on
   127.0.0.1): the recording must be byte-identical to 1;
3. ``vtcal measure --order plan --gain 0.9``: the earlier loop, on the plan's order;
4. the paper's loop in process: the plan's order, the scenario's own settings (its gain,
   the Jacobian probed once per target and never updated), the loop the simulator records
   with.

For each: touch-ups converged, captures per converged touch-up split into probes, loop
iterations and extra captures, cell (simulated robot) time per touch-up (median) and per
calibration, and the cell time split into travel, settle, servo and capture
(:mod:`pipeline.live.timing`; per touch-up the mean, so that the four add up to the mean
touch-up); then ``vtcal run`` on the recording and the calibrated pin's shape and absolute
RMS error against the simulation truth over 500 poses (``pipeline.accuracy.evaluate.judge_run``).

    python benchmarks/bench_measure.py [--scenario datasets/scenarios/standard.toml] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.accuracy.evaluate import judge_run
from pipeline.commands.measure import HOLD_S, run_measure
from pipeline.live.detector import vtcal_detector
from pipeline.live.plan_file import read_plan
from pipeline.live.record import open_recording
from pipeline.live.session import SessionOptions, goal_from_metadata, run_session
from pipeline.live.summary import summarize
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.sim.adapters import connect
from pipeline.sim.link import sim_cell, write_plan

REPO = Path(__file__).resolve().parent.parent


def truth_of(spec: str) -> dict[str, Any]:
    """What judge_run needs of the simulated cell's truth."""
    cell, _ = sim_cell(spec)
    c = cell.sess.cell
    sc = cell.sess.sc
    return {
        "base_link": sc.robot.base_link,
        "flange_link": sc.robot.flange_link,
        "true_urdf": c.true_urdf,
        "nominal_urdf": c.nominal_urdf,
        "joint_names": c.nominal.joint_names,
        "p_vt_flange": c.p_vt_flange.tolist(),
    }


def paper_loop(spec: str, plan_path: Path, out: Path) -> dict[str, Any]:
    """The plan measured with the scenario's own loop settings (fixed J per target)."""
    link = connect(spec, None)
    cell, _ = sim_cell(spec)  # the same cell, for its loop settings only
    cfg = cell.loop_config()
    from dataclasses import replace

    cfg = replace(cfg, compute_s=max(cfg.compute_s, HOLD_S))
    plan = read_plan(plan_path, link.robot.joint_names)
    goal = goal_from_metadata(link.metadata, None)
    link.drain_joints()
    rec = open_recording(
        out,
        link.urdf or "",
        link.metadata,
        plan.sha256,
        len(plan),
        link.robot.read_joints().stamp_ns,
    )
    detect = vtcal_detector(goal.polarity, size_px=goal.s0)
    run_session(link, plan, rec, goal, cfg, detect, SessionOptions(), lambda ev: None)
    rec.finish()
    return summarize(rec.progress.touchups, len(plan), 1, out)


def calibrate(rec: Path, truth: dict[str, Any], work: Path) -> dict[str, float]:
    out = work / (rec.stem + "_run")
    t0 = time.perf_counter()
    run_pipeline(rec, out, RunConfig(report=False), until="crossval")
    t_run = time.perf_counter() - t0
    j = judge_run(out, truth, 500, 1)
    return {
        "shape_rms_mm": j["after"]["shape_rms_m"] * 1e3,
        "abs_rms_mm": j["after"]["abs_rms_m"] * 1e3,
        "before_mm": j["before"]["shape_rms_m"] * 1e3,
        "n_used": float(j["model_summary"].get("n_used", np.nan)),
        "run_s": t_run,
    }


def breakdown(rec: Path) -> dict[str, float]:
    """Probe, loop and extra captures per converged touch-up, median cell and wall time per
    touch-up, and the cell time's split (progress file)."""
    p = json.loads(rec.with_name(rec.name + ".progress.json").read_text())
    tus = p["touchups"]
    conv = [t for t in tus if t["converged"]]
    n = max(len(conv), 1)
    probes = sum(t["probe_captures"] for t in tus)
    loops = sum(t["iterations"] for t in tus)
    extras = sum(t["captures"] - t["probe_captures"] - t["iterations"] for t in tus)
    cell_s = np.array([t["cell_s"] for t in tus])
    wall_s = np.array([t["wall_s"] for t in tus])
    return {
        "probes": probes / n,
        "loop": loops / n,
        "extras": extras / n,
        "cell_med": float(np.median(cell_s)),
        "wall_med": float(np.median(wall_s)),
        "iter_max": max(t["iterations"] for t in tus),
        **{k: sum(t[k] for t in tus) for k in SPLIT},
        "n": len(tus),
    }


#: the split of the cell time (pipeline.live.timing), as the touch-up summaries keep it
SPLIT = ("travel_s", "settle_s", "servo_s", "capture_s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(REPO / "datasets" / "scenarios" / "standard.toml"))
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    spec = f"sim:{args.scenario}:{args.seed}"
    truth = truth_of(spec)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        plan = work / "plan.parquet"
        cell, _ = sim_cell(spec)
        write_plan(cell, str(plan))
        rows: dict[str, dict[str, Any]] = {}
        # run_measure(plan, robot, camera, out, urdf, set, speed, max_iterations, gain,
        #             limit_margin_deg, quiet, dry_run, order): the CLI's defaults
        new = (0.5, 12, 1.0, 0.0, True, False, "travel")

        t0 = time.perf_counter()
        s = run_measure(plan, spec, None, work / "sim.mcap", None, {}, *new)
        rows["vtcal measure --order travel, sim:"] = {**s, "total_wall": time.perf_counter() - t0}

        server = subprocess.Popen(
            [sys.executable, "-m", "pipeline", "cell-server", "--scenario", args.scenario,
             "--seed", str(args.seed), "--port", "0"],
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert server.stderr is not None
            line = server.stderr.readline()
            url = line.split()[2]
            t0 = time.perf_counter()
            s = run_measure(plan, url, None, work / "tcp.mcap", None, {}, *new)
            rows["vtcal measure --order travel, tcp://"] = {
                **s,
                "total_wall": time.perf_counter() - t0,
            }
        finally:
            server.terminate()
            server.wait()

        t0 = time.perf_counter()
        s = run_measure(
            plan, spec, None, work / "before.mcap", None, {}, 0.5, 12, 0.9, 0.0, True, False, "plan"
        )
        rows["before: --order plan --gain 0.9, sim:"] = {
            **s,
            "total_wall": time.perf_counter() - t0,
        }

        t0 = time.perf_counter()
        s = paper_loop(spec, plan, work / "paper.mcap")
        rows["paper's loop (fixed J), plan order"] = {**s, "total_wall": time.perf_counter() - t0}

        same = (work / "sim.mcap").read_bytes() == (work / "tcp.mcap").read_bytes()
        print(f"{args.scenario} seed {args.seed}: {len(cell.plan)} planned touch-ups")
        print(f"in-process and TCP recordings byte-identical: {same}")
        hdr = (
            f"{'loop':38s} {'conv':>7s} {'captures/conv':>13s} {'= probe+loop+extra':>19s} "
            f"{'cell s/tu':>9s} {'cell s':>7s} {'wall s':>7s} "
            f"{'shape mm':>8s} {'abs mm':>7s} {'nominal':>7s}"
        )
        print(hdr)
        splits = {}
        for name, s in rows.items():
            rec = Path(s["recording"])
            b = breakdown(rec)
            splits[name] = b
            acc = calibrate(rec, truth, work)
            print(
                f"{name:38s} {s['converged']:>3d}/{s['touchups']:<3d} "
                f"{s['captures_per_converged']:13.2f} "
                f"{b['probes']:6.2f}+{b['loop']:5.2f}+{b['extras']:5.2f} "
                f"{b['cell_med']:9.2f} {s['cell_s']:7.1f} {s['wall_s']:7.1f} "
                f"{acc['shape_rms_mm']:8.4f} {acc['abs_rms_mm']:7.4f} {acc['before_mm']:7.4f}"
            )
        print(
            "cell s/tu: median per touch-up (large move to last capture); cell s, wall s: the "
            "whole measurement; shape/abs: calibrated pin RMS vs truth over 500 poses; nominal: "
            "the uncalibrated robot's shape RMS"
        )
        print()
        print(
            f"{'cell time split':38s} {'per touch-up (mean), s':>34s}   {'per calibration, s':>34s}"
        )
        cols = " ".join(f"{k[:-2]:>8s}" for k in SPLIT)
        print(f"{'loop':38s} {cols}   {cols} {'sum':>7s} {'cell s':>7s}")
        for name, b in splits.items():
            per = " ".join(f"{b[k] / b['n']:8.3f}" for k in SPLIT)
            tot = " ".join(f"{b[k]:8.1f}" for k in SPLIT)
            total = sum(b[k] for k in SPLIT)
            print(f"{name:38s} {per}   {tot} {total:7.1f} {rows[name]['cell_s']:7.1f}")
        print(
            "travel: large moves until arrived; servo: probing shifts and servo steps until "
            "arrived; settle: arrival to the next exposure; capture: exposure, detection and "
            "the hold after it (pipeline/live/timing.py)"
        )


if __name__ == "__main__":
    main()
