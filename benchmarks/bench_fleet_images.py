"""Benchmark: an image-level fleet through ``vtcal batch`` then ``vtcal audit``, against
the time the stock readers take to read and decode the same files.

    python benchmarks/bench_fleet_images.py [--robots 10] [--recordings 4] [--workdir DIR]
                                            [--workers 2] [--no-dask]

``--robots`` robots of the LR Mate-like model (each its own cell seed and ``robot_id``),
``--recordings`` recordings each (``vtcal simulate``, seeds 1..N, 3 targets on a bar x 6
poses, one capture at convergence), simulated once into ``--workdir`` (kept: a second
run of the benchmark reuses them). Then, timed as a user runs them:

1. the *read floor*: each file read and every message decoded by the stock ``mcap`` +
   ``mcap_ros2`` readers, images made arrays (``bench_run_stages.read_floor``), one fresh
   process per file; their sum divided by ``--workers`` is what ``--workers`` cores need
   at the least to read the fleet;
2. ``vtcal batch`` of every recording with ``--workers`` processes (every stage, report
   included), into a fresh folder: wall time and its ratio to the floor per core (goal
   <= 1.5); then the same with ``--executor dask`` (a local cluster of ``--workers``
   single-threaded workers) unless ``--no-dask``;
3. ``vtcal audit`` of the batch's run folders on the same kind of executor.

Each batch also prints the CPU seconds of a worker's first recording against its later
ones (``summary.parquet``): what a fresh worker pays (``pipeline/batch/warm.py``).

Printed: each figure measured in this one run, the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def vtcal(*args: str, quiet: bool = True) -> float:
    """Wall seconds of one ``vtcal`` command in a fresh process (exit 0 or 3 accepted)."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL if quiet else None,
        stderr=subprocess.PIPE,
        text=True,
    )
    took = time.perf_counter() - t0
    if proc.returncode not in (0, 3):
        raise SystemExit(f"vtcal {' '.join(args)}: exit {proc.returncode}: {proc.stderr[-2000:]}")
    return took


def _simulate(job: tuple[Path, str, int]) -> Path:
    rec, text, seed = job
    if not rec.is_file():
        toml = rec.with_suffix(".toml")
        toml.write_text(text)
        vtcal(
            "simulate", "--scenario", str(toml), "--seed", str(seed), "--out", str(rec), "--quiet"
        )
    return rec


def simulate(work: Path, robots: int, recordings: int, workers: int) -> list[Path]:
    """The fleet's recordings (made once, kept in ``work``)."""
    from bench_audit_images import scenario

    jobs = []
    for r in range(robots):
        text = scenario(3000 + r, f"fleet-{r:02d}", 0.0, 0.0, 6)
        for s in range(1, recordings + 1):
            jobs.append((work / f"fleet-{r:02d}-{s}.mcap", text, s))
    with ProcessPoolExecutor(workers) as ex:
        return list(ex.map(_simulate, jobs))


def floor_seconds(recs: list[Path]) -> float:
    """Sum over the files of the stock readers' read + decode wall time (fresh processes)."""
    from bench_run_stages import floor_process

    return sum(floor_process(r)[0] for r in recs)


def first_vs_later(out: Path) -> str:
    """CPU seconds of each worker's first recording against its later ones (summary.parquet)."""
    import pandas as pd

    s = pd.read_parquet(out / "summary.parquet")
    k = s.groupby("worker").cumcount()
    first, later = s.loc[k == 0, "cpu_seconds"], s.loc[k > 0, "cpu_seconds"]
    return (
        f"CPU per recording: a worker's first {first.median():.2f} s (n {len(first)}), "
        f"later ones {later.median():.2f} s (median, n {len(later)})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--recordings", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_fleet_images"))
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask cluster's batch")
    ap.add_argument("--prepare", action="store_true", help="only simulate the recordings")
    a = ap.parse_args()
    a.workdir.mkdir(parents=True, exist_ok=True)
    print(f"load before: {load()}  (cores: {os.cpu_count()})", flush=True)
    t0 = time.perf_counter()
    recs = simulate(a.workdir, a.robots, a.recordings, a.workers)
    print(f"{len(recs)} recordings ({a.robots} robots x {a.recordings}) ready in "
          f"{time.perf_counter() - t0:.0f} s, {sum(r.stat().st_size for r in recs) / 1e6:.1f} MB",
          flush=True)  # fmt: skip
    if a.prepare:
        return
    floor = floor_seconds(recs)
    per_core = floor / a.workers
    print(f"read floor (stock mcap + mcap_ros2 readers, every message decoded, fresh process "
          f"per file): {floor:.2f} s in all, {per_core:.2f} s per core at {a.workers} cores",
          flush=True)  # fmt: skip
    runs: dict[str, Path] = {}
    for kind in ("processes", *(() if a.no_dask else ("dask",))):
        out = a.workdir / f"runs_{kind}"
        shutil.rmtree(out, ignore_errors=True)
        took = vtcal("batch", *map(str, recs), "--out", str(out), "--workers", str(a.workers),
                     "--executor", kind)  # fmt: skip
        runs[kind] = out
        print(f"vtcal batch --executor {kind} --workers {a.workers}: {took:.1f} s, "
              f"{took / per_core:.2f}x the read floor per core (goal <= 1.5: "
              f"{'met' if took / per_core <= 1.5 else 'NOT met'}); "
              f"{took / len(recs):.2f} s per recording", flush=True)  # fmt: skip
        print("  " + first_vs_later(out), flush=True)
    for kind, out in runs.items():
        audit = a.workdir / f"audit_{kind}"
        shutil.rmtree(audit, ignore_errors=True)
        took = vtcal("audit", str(out), "--out", str(audit), "--workers", str(a.workers),
                     "--executor", kind)  # fmt: skip
        print(f"vtcal audit --executor {kind} of the batch's {len(recs)} run folders: "
              f"{took:.1f} s", flush=True)  # fmt: skip
    print(f"load after: {load()}")


if __name__ == "__main__":
    main()
