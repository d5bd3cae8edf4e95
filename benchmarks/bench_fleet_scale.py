"""Benchmark: a fleet at scale: ``vtcal audit`` over N robots x M recordings, then one more each.

    python benchmarks/bench_fleet_scale.py [--robots 500] [--recordings 4] [--work DIR]
        [--no-serial] [--no-dask]

Touch-up-level recordings (:func:`pipeline.sim.history.make_history`, 3 targets x 6
touch-ups, a calibration bar; every robot its own seed) are written as run folders
(:func:`pipeline.sim.history.write_history`) into ``WORK/runs``. Then ``vtcal audit
WORK/runs`` runs as a subprocess, each into a fresh ``--out``:

* ``--workers 1`` (in one process), ``--workers 2`` (the process pool) and
  ``--executor dask --workers 2`` (a local Dask cluster of two workers): wall time,
  peak memory (the largest process, ``ru_maxrss`` of ``wait4``; and the whole process
  tree's resident memory, sampled every 0.2 s with psutil when installed), the
  speed-ups, and the tables compared with the serial ones (equal, and the same
  changes read);
* **incremental**: one more recording per robot is written (recording M of each
  history: the first M are those already there), and ``vtcal audit`` runs again into
  the ``--workers 2`` folder: its wall time against its share (the full audit's time
  per recording times the new recordings: full time x new / N x M), and the old recordings fitted again (from its ``fits:`` line;
  must be 0).

Goals: 2000 recordings within 10 min on 2 cores, peak memory under 4 GiB, the
incremental audit within 20 % of its share.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PER_TARGET = 6
GIB = 1024**3


def _write_robot(args: tuple[int, int, str, bool]) -> int:
    from pipeline.sim.history import make_history, write_history

    r, n, out, only_last = args
    hist = make_history(f"R{r:04d}", n_recordings=n, seed=1000 + r, per_target=PER_TARGET)
    return len(write_history(hist[-1:] if only_last else hist, Path(out)))


def write_fleet(runs: Path, robots: int, n: int, only_last: bool = False) -> int:
    """Write every robot's history (or only its last recording) in two processes."""
    import multiprocessing as mp

    jobs = [(r, n, str(runs), only_last) for r in range(robots)]
    with mp.get_context("fork").Pool(2) as pool:
        return sum(pool.map(_write_robot, jobs, chunksize=8))


def _tree_rss(pid: int) -> int:
    import psutil

    try:
        p = psutil.Process(pid)
        procs = [p, *p.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_audit_cli(runs: Path, out: Path, *args: str) -> dict[str, object]:
    """``vtcal audit runs --out out ARGS`` as a subprocess: seconds, peak memory, output."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "pipeline", "audit", str(runs), "--out", str(out), *args]
    t0 = time.perf_counter()
    log = out.with_suffix(".log")
    with log.open("w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
        peak = [0]
        stop = threading.Event()

        def sample() -> None:
            try:
                import psutil  # noqa: F401
            except ImportError:
                return
            while not stop.is_set():
                peak[0] = max(peak[0], _tree_rss(proc.pid))
                stop.wait(0.2)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        stop.set()
        th.join()
    seconds = time.perf_counter() - t0
    text = log.read_text()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{text[-3000:]}")
    m = re.search(r"fits: (\d+) new, (\d+) cached", text)
    return {
        "s": seconds,
        "maxrss": usage.ru_maxrss * 1024,
        "tree": peak[0],
        "work": next((ln for ln in text.splitlines() if ln.startswith("fits:")), ""),
        "fits_new": int(m.group(1)) if m else -1,
    }


def compare_tables(a: Path, b: Path) -> tuple[bool, bool]:
    """(every table equal, the same changes read) of two audit folders."""
    import pandas as pd

    equal = True
    for name in ("audit_recordings", "audit_changes", "audit_models"):
        ta, tb = pd.read_parquet(a / f"{name}.parquet"), pd.read_parquet(b / f"{name}.parquet")
        try:
            pd.testing.assert_frame_equal(ta, tb, check_exact=True)
        except AssertionError:
            equal = False
    cols = ["from_recording", "to_recording", "changed", "kind", "cause"]
    ca = pd.read_parquet(a / "audit_changes.parquet")[cols]
    cb = pd.read_parquet(b / "audit_changes.parquet")[cols]
    return equal, bool(ca.equals(cb))


def _mem(r: dict[str, object]) -> str:
    tree = f", process tree {int(r['tree']) / GIB:.2f} GiB" if r["tree"] else ""
    return f"largest process {int(r['maxrss']) / GIB:.2f} GiB{tree}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=500)
    ap.add_argument("--recordings", type=int, default=4)
    ap.add_argument(
        "--work", type=Path, default=None, help="work folder (default: a temporary one)"
    )
    ap.add_argument("--no-serial", action="store_true", help="skip the --workers 1 audit")
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask audit")
    a = ap.parse_args()
    work = a.work or Path(tempfile.mkdtemp(prefix="vtcal_fleet_"))
    if work.exists():
        shutil.rmtree(work)
    runs = work / "runs"
    runs.mkdir(parents=True)
    n, N = a.recordings, a.robots * a.recordings
    print(f"fleet: {a.robots} robots x {n} recordings = {N} run folders (touch-up level, "
          f"{PER_TARGET} touch-ups x 3 targets), {os.cpu_count()} cores; work {work}")  # fmt: skip
    t = time.perf_counter()
    write_fleet(runs, a.robots, n)
    print(f"written in {time.perf_counter() - t:.1f} s")

    configs = [("serial", ("--workers", "1"))] if not a.no_serial else []
    configs.append(("processes", ("--workers", "2")))
    if not a.no_dask:
        configs.append(("dask", ("--executor", "dask", "--workers", "2")))
    res = {}
    for name, args in configs:
        res[name] = run_audit_cli(runs, work / f"audit_{name}", *args)
        r = res[name]
        print(f"audit {name:<9} {' '.join(args):<30} {r['s']:7.1f} s  {_mem(r)}  [{r['work']}]")
    base = "serial" if "serial" in res else "processes"
    for name in res:
        if name != base:
            eq, same = compare_tables(work / f"audit_{base}", work / f"audit_{name}")
            print(f"{name} vs {base}: speed-up x{float(res[base]['s']) / float(res[name]['s']):.2f}; "  # type: ignore[arg-type]
                  f"tables equal: {'yes' if eq else 'NO'}; same changes read: {'yes' if same else 'NO'}")  # fmt: skip

    t = time.perf_counter()
    write_fleet(runs, a.robots, n + 1, only_last=True)
    print(f"one more recording per robot written in {time.perf_counter() - t:.1f} s")
    full = float(res["processes"]["s"])  # type: ignore[arg-type]
    inc = run_audit_cli(runs, work / "audit_processes", "--workers", "2")
    share = full * a.robots / N  # the full audit's time per recording, for the new ones
    refits = int(inc["fits_new"]) - a.robots  # type: ignore[call-overload]
    ratio = float(inc["s"]) / share  # type: ignore[arg-type]
    print(f"incremental --workers 2: {inc['s']:.1f} s for {a.robots} new recordings "
          f"({N + a.robots} in all); its share: the full audit's {full:.1f} s x "
          f"{a.robots}/{N} = {share:.1f} s (x{ratio:.2f}); old recordings fitted again: "
          f"{refits}; {_mem(inc)}  [{inc['work']}]")  # fmt: skip

    scale = 2000 / N
    peak = max(max(int(r["maxrss"]), int(r["tree"])) for r in [*res.values(), inc])  # type: ignore[call-overload]
    print("goals:")
    print(f"  2000 recordings within 10 min on 2 cores: {full:.1f} s for {N}"
          + (f" (x{scale:g}: {full * scale:.0f} s)" if N != 2000 else "")
          + f" -> {'met' if full * scale <= 600 else 'NOT met'}")  # fmt: skip
    print(f"  peak memory under 4 GiB: {peak / GIB:.2f} GiB -> {'met' if peak < 4 * GIB else 'NOT met'}")  # fmt: skip
    ok = ratio <= 1.2 and refits == 0
    print(f"  incremental within 20 % of its share, no old recording fitted again: "
          f"x{ratio:.2f} of its share, {refits} refitted -> {'met' if ok else 'NOT met'}")  # fmt: skip
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
