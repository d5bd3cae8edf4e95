"""Benchmark: batch reprocessing of 8 simulated recordings on 1 and 2 workers, then cached.

Simulates 8 recordings of the small scenario (``datasets/scenarios/small.toml``,
seeds 1..8) into a temporary folder (two simulations at a time), writes a
manifest for them, then times, in this one run:

1. the batch on 1 worker (process pool) into a fresh folder,
2. the batch on 2 workers into another fresh folder: speed-up = (1) / (2),
   target >= 1.7,
   (each timed ``--repeat`` times, alternating 1 and 2 workers so both see the
   same background load; the best of each is used),
3. the same batch again with nothing changed (every stage cached) in this
   process: ratio (3) / (2), target < 0.10,
4. the same cached batch as a user runs it, a cold ``vtcal batch --manifest``
   process (interpreter start, imports, the run ledger's checks; no worker pool is
   started when nothing changed): ratio (4) / (2), target < 0.10 (median of 3),
5. peak RSS (``getrusage`` ``ru_maxrss``) of every worker process after its first
   and after its last recording: memory per worker is bounded when it does not
   grow with the recordings a worker has processed.

The process pool's fork server (one interpreter that imports the pipeline once,
then forks every worker) is started before the timed runs and its start-up
time printed apart: (1) and (2) then compare the work, not the imports; (4)
includes every start-up cost.

The identify stage uses the ``offsets`` error model: 3 targets x 2 poses are too
few touch-ups for the full model (the batch would report them as
calibration_failed, which is a valid batch but not the workload meant here).
Wall times depend on what else runs on the machine: the load average is printed
before and after, and for every timed batch the CPU other processes took
meanwhile (``/proc/stat`` busy time minus our tasks' CPU time): a speed-up
can only show when the second core is not busy with someone else's work. As a
yardstick, the throughput of two concurrent busy-loop processes relative to one
is measured before and after (2.0 on two free cores), and the batch speed-up
is also printed relative to it.

    python benchmarks/bench_batch.py [--until identify] [--workdir DIR] [--seeds 8]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "datasets" / "scenarios" / "small.toml"


def simulate(workdir: Path, seeds: int) -> list[Path]:
    """Simulate the recordings that are not there yet, two at a time."""
    paths = [workdir / f"small_s{s}.mcap" for s in range(1, seeds + 1)]
    todo = [(s, p) for s, p in enumerate(paths, start=1) if not p.exists()]

    def one(sp: tuple[int, Path]) -> None:
        s, p = sp
        cmd = ["vtcal", "simulate", "--scenario", str(SCENARIO), "--seed", str(s)]
        subprocess.run([*cmd, "--out", str(p), "--quiet"], check=True)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(one, todo))
    if todo:
        print(f"simulated {len(todo)} recording(s) in {time.perf_counter() - t0:.1f} s")
    return paths


def write_manifest(workdir: Path, paths: list[Path]) -> Path:
    m = workdir / "bench.toml"
    lines = ['name = "bench_batch"', 'description = "small scenario, seeds 1..N"', ""]
    for p in paths:
        lines += ["[[recordings]]", f'path = "{p.name}"', 'robot = "lrmate"', ""]
    m.write_text("\n".join(lines))
    return m


BURN = "x = 0\nfor i in range(20_000_000):\n    x += i\n"


def machine_parallelism() -> float:
    """Throughput of 2 concurrent pure-Python busy loops relative to 1 (2.0 on 2 free cores).

    The yardstick for the batch speed-up: what this machine delivers right now to
    two independent CPU-bound processes, whatever else runs on it.
    """

    def burn(n: int) -> float:
        t0 = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", BURN]) for _ in range(n)]
        for p in procs:
            p.wait()
        return time.perf_counter() - t0

    one = burn(1)
    two = burn(2)
    return 2.0 * one / two


def cpu_busy_seconds() -> float:
    """Core-seconds the whole machine spent busy so far (``/proc/stat``; 0 elsewhere)."""
    try:
        f = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return 0.0
    idle = f[3] + (f[4] if len(f) > 4 else 0)
    return (sum(f[:8]) - idle) / os.sysconf("SC_CLK_TCK")


RECYCLE = 10


def timed_batch(items, out: Path, workers: int, until: str, cfg) -> tuple[float, object]:
    """Run a batch; also print how much CPU other processes took meanwhile."""
    from pipeline.batch.run import run_batch

    b0, t0 = cpu_busy_seconds(), time.perf_counter()
    res = run_batch(
        items, out, cfg, kind="processes", workers=workers, until=until, recycle_after=RECYCLE
    )
    dt, busy = time.perf_counter() - t0, cpu_busy_seconds() - b0
    ours = sum(o.cpu_seconds for o in res.outcomes)
    others = max(0.0, busy - ours)
    print(
        f"    {workers} worker(s): {dt:.2f} s; our tasks {ours:.1f} CPU-s, other processes "
        f"on the machine {others:.1f} CPU-s ({others / dt:.2f} cores busy with them)"
    )
    return dt, res


def rss_by_worker(outcomes) -> dict[str, list[tuple[float, float]]]:
    """worker -> (peak RSS, RSS now) after each of its recordings, in the order it ran them.

    Peak RSS only grows within a process, so sorting by it (then by the item
    order, stable) gives the order.
    """
    per: dict[str, list[tuple[float, float]]] = {}
    for o in outcomes:
        if o.peak_rss_mb is not None:
            per.setdefault(o.worker, []).append((o.peak_rss_mb, o.rss_mb or float("nan")))
    return {w: sorted(v, key=lambda x: x[0]) for w, v in per.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--until", default="report", help="last stage (default: report, all)")
    ap.add_argument("--workdir", type=Path, default=None, help="keep recordings here")
    ap.add_argument("--seeds", type=int, default=8, help="number of recordings (8)")
    ap.add_argument("--repeat", type=int, default=2, help="timed 1/2-worker pairs (2)")
    ap.add_argument("--recycle", type=int, default=10, help="worker replaced after N (10)")
    args = ap.parse_args()
    global RECYCLE
    RECYCLE = args.recycle

    from pipeline.batch.run import load_manifest, open_executor
    from pipeline.run.orchestrator import RunConfig

    tmp = tempfile.TemporaryDirectory(prefix="bench_batch_")
    workdir = args.workdir or Path(tmp.name)
    workdir.mkdir(parents=True, exist_ok=True)
    paths = simulate(workdir, args.seeds)
    size_mb = sum(p.stat().st_size for p in paths) / 1e6
    manifest = write_manifest(workdir, paths)
    items = list(load_manifest(manifest).items)
    cfg = RunConfig(stage_options={"identify": {"model": "offsets"}})
    print(
        f"{len(items)} recordings ({size_mb:.0f} MB), until {args.until}, "
        f"cores {os.cpu_count()}, load average before {os.getloadavg()[0]:.2f}"
    )

    t0 = time.perf_counter()
    with open_executor("processes", 2) as pool:  # start the fork server, let it preload
        [f.result() for f in [pool.submit(os.getpid) for _ in range(2)]]
    print(f"fork server start (imports the pipeline once): {time.perf_counter() - t0:.2f} s")

    cap_before = machine_parallelism()
    print(f"machine: 2 busy loops at once ran x{cap_before:.2f} the throughput of 1 (2.00 if free)")
    stamp = time.strftime("%H%M%S")
    t1s: list[float] = []
    t2s: list[float] = []
    for k in range(args.repeat):  # alternate, so both see the same background load
        out1 = workdir / f"out_{stamp}_{k}_w1"
        out2 = workdir / f"out_{stamp}_{k}_w2"
        t1, r1 = timed_batch(items, out1, 1, args.until, cfg)
        t2, r2 = timed_batch(items, out2, 2, args.until, cfg)
        t1s.append(t1)
        t2s.append(t2)
        f1, f2 = r1.timings["fan_out"], r2.timings["fan_out"]
        print(
            f"  repeat {k + 1}: 1 worker {t1:.2f} s, 2 workers {t2:.2f} s, x{t1 / t2:.2f}; "
            f"fan-out alone {f1:.2f} s vs {f2:.2f} s, x{f1 / f2:.2f}; "
            f"summary + compare {t2 - f2:.2f} s"
        )
    t1, t2 = min(t1s), min(t2s)
    t3, r3 = timed_batch(items, out2, 2, args.until, cfg)
    cli = ["vtcal", "batch", "--manifest", str(manifest), "--out", str(out2)]
    cli += ["--until", args.until, "--workers", "2", "--model", "offsets", "-q"]
    cli += ["--recycle", str(args.recycle)]
    t4s = []
    for _ in range(3):
        t0 = time.perf_counter()
        proc = subprocess.run(cli, capture_output=True, text=True)
        t4s.append(time.perf_counter() - t0)
    t4 = sorted(t4s)[1]

    for name, r in (("1 worker", r1), ("2 workers", r2), ("cached", r3)):
        ok = sum(o.status == "ok" for o in r.outcomes)
        ran = sum(st == "ran" for o in r.outcomes for _, st, _ in o.stages)
        cached = sum(st == "cached" for o in r.outcomes for _, st, _ in o.stages)
        secs = [o.seconds for o in r.outcomes]
        print(
            f"  {name:<9}: {ok}/{len(r.outcomes)} ok, stages ran {ran}, cached {cached}; "
            f"task wall times sum {sum(secs):.2f} s, max {max(secs):.2f} s, "
            f"CPU {sum(o.cpu_seconds for o in r.outcomes):.2f} s"
        )
        for o in r.failed:
            print(f"    {o.name}: {o.error_kind}: {o.error}")
    if proc.returncode != 0:
        print(f"  cli exit {proc.returncode}: {proc.stderr.strip()[-300:]}")

    failed = sum(len(r.failed) for r in (r1, r2, r3))
    if failed:
        print(f"WARNING: {failed} recording run(s) failed: the timings below are not the workload")
    per_rec = sorted(o.seconds for o in r1.outcomes)
    print(f"per recording on 1 worker: median {per_rec[len(per_rec) // 2]:.2f} s")
    print(f"batch, 1 worker (best of {args.repeat}):  {t1:7.2f} s")
    print(f"batch, 2 workers (best of {args.repeat}): {t2:7.2f} s")
    print(f"speed-up 2 workers vs 1:         {t1 / t2:7.2f} x   (target >= 1.7)")
    cap_after = machine_parallelism()
    cap = 0.5 * (cap_before + cap_after)
    print(
        f"  the machine's own 2-process throughput: x{cap_before:.2f} before, x{cap_after:.2f} "
        f"after; batch speed-up / machine's = {t1 / t2 / cap:.2f}"
    )
    print(f"second run, nothing changed:     {t3:7.2f} s")
    print(f"  ratio to the first (2 workers):  {t3 / t2:7.3f}     (target < 0.10)")
    print(
        f"second run as a cold CLI process: {t4:6.2f} s   "
        f"(median of {', '.join(f'{t:.2f}' for t in t4s)})"
    )
    print(f"  ratio to the first (2 workers):  {t4 / t2:7.3f}     (target < 0.10)")
    print("memory per worker (MB): peak RSS (getrusage ru_maxrss) first -> last recording;")
    print("  then RSS at the end of each recording (/proc/self/statm)")
    for label, r in (("1 worker", r1), ("2 workers", r2)):
        for w, seq in rss_by_worker(r.outcomes).items():
            print(
                f"  {label:<9} {w:<16} peak {seq[0][0]:6.1f} -> {seq[-1][0]:6.1f} "
                f"(x{seq[-1][0] / seq[0][0]:.3f}, {len(seq)} recordings); "
                f"RSS after each: {' '.join(f'{x[1]:.0f}' for x in seq)}"
            )
    import resource

    parent = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"  parent process (this benchmark): {parent:.1f} MB")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    tmp.cleanup()


if __name__ == "__main__":
    sys.exit(main())
