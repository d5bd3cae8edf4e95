"""Benchmark: generation time and peak memory of the simulator.

Runs the standard scenario (LR Mate-like, 3 targets x 12 poses, 640 x 512 PNG)
on one core in a child process, and the same cell with 4 poses per target, and
prints wall and CPU time (CPU time is what one free core would take; wall
time grows when the machine is shared), per-image time, file size and peak RSS (``ru_maxrss``) of
each, plus the ratios (time against the 60 s target; memory of the long run
against the short one: streaming means it must not grow with the recording).

    python benchmarks/bench_simulate.py [--seed N]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(scenario: str, per_target: int, seed: int, out: str) -> None:
    import dataclasses
    import resource
    import time

    import cv2

    cv2.setNumThreads(1)
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import write_recording

    sc = load_scenario(scenario)
    sc = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, per_target=per_target))
    t0 = time.perf_counter()
    truth = write_recording(sc, seed, Path(out))
    dt = time.perf_counter() - t0
    ru = resource.getrusage(resource.RUSAGE_SELF)
    rss_mb = ru.ru_maxrss / 1024.0
    print(
        json.dumps(
            {
                "seconds": dt,
                "cpu_seconds": ru.ru_utime + ru.ru_stime,
                "images": truth["counts"]["images"],
                "joint_states": truth["counts"]["joint_states"],
                "touchups": truth["counts"]["touchups"],
                "converged": sum(t["converged"] for t in truth["touchups"]),
                "bytes": Path(out).stat().st_size,
                "peak_rss_mb": rss_mb,
            }
        )
    )


def run(per_target: int, seed: int, tmp: str) -> dict[str, float]:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = str(Path(tmp) / f"bench_{per_target}.mcap")
    scen = str(ROOT / "datasets" / "scenarios" / "standard.toml")
    cmd = [sys.executable, __file__, "--child", scen, str(per_target), str(seed), out]
    if sys.platform.startswith("linux"):
        cmd = ["taskset", "-c", "0", *cmd]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--child", nargs=4)
    a = ap.parse_args()
    if a.child:
        child(a.child[0], int(a.child[1]), int(a.child[2]), a.child[3])
        return
    with tempfile.TemporaryDirectory() as tmp:
        short = run(4, a.seed, tmp)
        full = run(12, a.seed, tmp)
    for name, r in (("3 targets x 4 poses ", short), ("3 targets x 12 poses", full)):
        print(
            f"{name}: {r['seconds']:6.1f} s wall, {r['cpu_seconds']:6.1f} s CPU  "
            f"{r['images']:4d} images "
            f"({1000 * r['seconds'] / r['images']:5.1f} ms/image)  {r['joint_states']:6d} joint states  "
            f"{r['converged']}/{r['touchups']} converged  {r['bytes'] / 1e6:6.1f} MB  "
            f"peak RSS {r['peak_rss_mb']:6.1f} MB"
        )
    print(
        f"standard scenario generation time / 60 s target: wall {full['seconds'] / 60.0:.2f}, "
        f"CPU {full['cpu_seconds'] / 60.0:.2f} (wall > CPU means the core was shared)"
    )
    print(
        f"peak RSS long / short run: {full['peak_rss_mb'] / short['peak_rss_mb']:.2f} "
        f"(recording {full['bytes'] / short['bytes']:.1f}x larger)"
    )


if __name__ == "__main__":
    main()
