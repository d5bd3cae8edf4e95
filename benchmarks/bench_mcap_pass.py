"""Benchmark: one streaming pass over every message of a recording, vtcal's reader against mcap's.

Ingest reads a recording once, record by record (``pipeline.io.mcap.iter_messages``).
Before, that pass was the ``mcap`` library's ``StreamReader`` (which parses
every Message Index entry by entry) and ``breakup_chunk`` (five stream reads per
message); now it is ``pipeline.io.mcap_records`` (index records read past whole,
one ``struct`` call per message). For the shipped sample and the standard cells
of ``bench_run_stages`` (simulated into ``--workdir`` once, seed 7) this prints the
CPU seconds of one pass each way (messages only, nothing decoded), best of
``--repeat``, their ratio, and whether both yield the same messages.

    python benchmarks/bench_mcap_pass.py [--workdir DIR] [--repeat 5]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"


def recordings(workdir: Path) -> dict[str, Path]:
    """The shipped sample and ``bench_run_stages``' standard cells (simulated there once)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_run_stages

    return {"sample": SAMPLE, **bench_run_stages.simulate(workdir)}


def library_messages(path: Path) -> Iterator[Any]:
    """Every message, as vtcal's pass read them before (the mcap library's readers)."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(path, "rb", buffering=1 << 20) as f:
        for rec in StreamReader(f, emit_chunks=True).records:
            if isinstance(rec, Chunk):
                yield from (
                    r for r in breakup_chunk(rec, validate_crc=True) if isinstance(r, Message)
                )
            elif isinstance(rec, Message):
                yield rec


def vtcal_messages(path: Path) -> Iterator[Any]:
    """Every message by ``pipeline.io.mcap.iter_messages``."""
    from pipeline.io.mcap import StreamState, iter_messages

    yield from iter_messages(path, StreamState(str(path)))


def best_cpu(fn: Callable[[Path], Iterator[Any]], path: Path, repeat: int) -> tuple[float, int]:
    best, n = math.inf, 0
    for _ in range(repeat):
        t0 = time.process_time()
        n = sum(1 for _ in fn(path))
        best = min(best, time.process_time() - t0)
    return best, n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_mcap_pass"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    recs = recordings(args.workdir)
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}; CPU s, best of {args.repeat}")
    print(f"{'recording':<11}{'messages':>9}{'mcap':>8}{'vtcal':>8}{'ratio':>7}{'same':>6}")
    for label, rec in recs.items():
        t_lib, n = best_cpu(library_messages, rec, args.repeat)
        t_new, _ = best_cpu(vtcal_messages, rec, args.repeat)
        same = list(library_messages(rec)) == list(vtcal_messages(rec))
        print(
            f"{label:<11}{n:>9}{t_lib:>8.3f}{t_new:>8.3f}{t_lib / t_new:>7.2f}"
            f"{'yes' if same else 'NO':>6}"
        )


if __name__ == "__main__":
    main()
