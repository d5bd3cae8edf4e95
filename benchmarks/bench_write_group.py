"""What a stage waits for when it writes its files: one ``fsync`` after another, or together.

Every file vtcal writes is made durable before it replaces the old one
(:func:`pipeline.io.fileio.atomic_write_bytes`: a temporary sibling, ``fsync``,
``os.replace``). The identify stage writes nine files (three tables,
``models.json``, five URDFs). Inside :func:`pipeline.io.fileio.write_group` the
``fsync``-s run in threads at once and the file system commits them together;
the files land in the order written when the group ends. This script writes
``--files`` files of ``--kb`` kB into a temporary folder on the file system of
``--dir``, one after another and in a group, alternating, and prints the median
and range of each over ``--repeat`` rounds.

    python benchmarks/bench_write_group.py --dir /tmp
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from pipeline.io.fileio import atomic_write_bytes, write_group


def write_files(folder: Path, n: int, blob: bytes, grouped: bool) -> float:
    """Seconds to write ``n`` files of ``blob`` into ``folder`` (in one group or not)."""
    t0 = time.perf_counter()
    if grouped:
        with write_group():
            for i in range(n):
                atomic_write_bytes(folder / f"f{i}.bin", blob)
    else:
        for i in range(n):
            atomic_write_bytes(folder / f"f{i}.bin", blob)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", default=tempfile.gettempdir(), help="file system to write on")
    ap.add_argument("--files", type=int, default=9, help="files per stage (identify: 9)")
    ap.add_argument("--kb", type=int, default=30, help="size of each file, kB")
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args()
    blob = os.urandom(args.kb * 1024)
    times: dict[bool, list[float]] = {False: [], True: []}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for r in range(args.repeat):
            for grouped in (False, True) if r % 2 == 0 else (True, False):
                times[grouped].append(write_files(Path(tmp), args.files, blob, grouped))
    print(f"{args.files} files of {args.kb} kB on {args.dir}, {args.repeat} rounds, "
          f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")  # fmt: skip
    for grouped, label in ((False, "one after another"), (True, "in a write group")):
        t = sorted(times[grouped])
        print(
            f"  {label:18s} median {statistics.median(t) * 1e3:6.1f} ms "
            f"(range {t[0] * 1e3:.1f}-{t[-1] * 1e3:.1f})"
        )


if __name__ == "__main__":
    main()
