"""Benchmark: ingest with its images taken on a worker thread against taken inline.

Ingest reads records and joint states on one thread and hands the images (decode,
detection, the camera-response estimate) to a worker thread
(:mod:`pipeline.stages.ingest.image_worker`). This script ingests the standard
cells' recordings (``bench_run_stages.py``'s, from ``--workdir``; simulated there
when missing) in this process, alternately with the worker and with every image
taken inline on the reading thread (the way before), ``--repeat`` times each after
one warm-up, and prints per cell the median and least wall time and the median
process CPU of both, the tables checked equal. Numeric libraries are held to one
thread, as the CLI does. The load average is printed before and after: on a
busy 2-core machine there is no second core to overlap on.

    python benchmarks/bench_ingest_overlap.py [--workdir DIR] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.run.threads import prefer_one_thread  # noqa: E402

prefer_one_thread()


class _Inline:
    """Every image decoded and taken at once on the reading thread (no overlap)."""

    def __init__(self, *a: object) -> None:
        pass

    def decode(self, fn: Any, *args: Any) -> Future[Any]:
        fut: Future[Any] = Future()
        fut.set_result(fn(*args))
        return fut

    def submit(self, fn: Any, *args: Any) -> None:
        fn(*args)

    def drain(self) -> None:
        pass

    def __enter__(self) -> _Inline:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", default="/tmp/vtcal_bench_run_stages")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_run_stages

    import pipeline.stages.ingest.stage as ing
    from pipeline.stages.detect.detector import DetectConfig

    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    recs = bench_run_stages.simulate(work)
    worker = ing.ImageWorker
    print(f"load before: {_load()}  (cores: {os.cpu_count()})")
    print(f"{'cell':<10} {'images':>6}  {'worker: wall med/min, CPU':>28}  {'inline: same':>28}")
    for label, rec in recs.items():
        times: dict[str, list[tuple[float, float]]] = {"worker": [], "inline": []}
        tables: dict[str, Any] = {}
        for i in range(args.repeat + 1):
            for mode in ("worker", "inline"):
                ing.ImageWorker = worker if mode == "worker" else _Inline  # type: ignore[misc]
                t0, c0 = time.perf_counter(), time.process_time()
                frames, dets, _ = ing.ingest_recording(rec, ing.IngestConfig(), DetectConfig())
                if i:  # the first round warms imports and compiled code
                    times[mode].append((time.perf_counter() - t0, time.process_time() - c0))
                tables[mode] = (frames, dets)
        ing.ImageWorker = worker  # type: ignore[misc]
        (f1, d1), (f2, d2) = tables["worker"], tables["inline"]
        assert f1.equals(f2) and d1.equals(d2), f"{label}: tables differ"
        cols = []
        for mode in ("worker", "inline"):
            wall = [w for w, _ in times[mode]]
            cpu = statistics.median(c for _, c in times[mode])
            cols.append(f"{statistics.median(wall):.3f} / {min(wall):.3f} s, {cpu:.3f} s")
        print(f"{label:<10} {len(d1):>6}  {cols[0]:>28}  {cols[1]:>28}", flush=True)
    print(f"load after: {_load()}")


if __name__ == "__main__":
    main()
