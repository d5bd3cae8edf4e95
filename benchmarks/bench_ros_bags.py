"""Reading a recording as ROS writes it: the shipped sample as MCAP, split rosbag2 MCAP,
rosbag2 sqlite3 and ROS 1 bag.

The sample (75 PNG images 640x512, 9,735 joint states) is converted with
rosbags' own writers (tests/support/rosbag_writers.py); then, for each container, in
one run:

- **stream**: every message through :func:`pipeline.io.recording.iter_recording`
  (container reading, plus ROS 1 -> ROS 2 CDR conversion for the ``.bag``);
- **ingest**: :func:`pipeline.stages.ingest.stage.ingest_recording` (stream, decode and
  detect every image, interpolate the joints);

each the best of 3 runs (the machine is shared), after one warm-up ingest
(numba's compiled detector loaded). Prints seconds and the ratio to the MCAP.

Usage: ``python benchmarks/bench_ros_bags.py``
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from support.rosbag_writers import (  # noqa: E402
    SAMPLE,
    StoragePlugin,
    sample_messages,
    with_touchup_topic,
    write_ros1_bag,
    write_rosbag2,
    write_split_mcap_bag,
)

from pipeline.io.layout import locate  # noqa: E402
from pipeline.io.mcap import StreamState  # noqa: E402
from pipeline.io.recording import iter_recording  # noqa: E402
from pipeline.stages.detect.detector import DetectConfig  # noqa: E402
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording  # noqa: E402


def best_of(fn, n: int = 3) -> float:  # type: ignore[no-untyped-def]
    best = float("inf")
    for _ in range(n):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def stream(path: Path) -> int:
    state = StreamState(str(path))
    return sum(1 for _ in iter_recording(locate(path), state))


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        msgs, meta = sample_messages()
        bag = with_touchup_topic(msgs, meta)
        recs = {
            "mcap": SAMPLE,
            "split mcap (3)": write_split_mcap_bag(d / "split", bag, 3),
            "db3": write_rosbag2(d / "db3", bag, StoragePlugin.SQLITE3),
            "ros1 .bag": write_ros1_bag(d / "rec.bag", bag),
        }
        ingest_recording(SAMPLE, IngestConfig(), DetectConfig())  # warm-up
        rows = []
        for name, p in recs.items():
            n = stream(p)
            t_s = best_of(lambda p=p: stream(p))
            t_i = best_of(lambda p=p: ingest_recording(p, IngestConfig(), DetectConfig()))
            rows.append((name, n, t_s, t_i))
        ref_s, ref_i = rows[0][2], rows[0][3]
        print(
            f"{'container':<16}{'messages':>9}{'stream s':>10}{'x mcap':>8}{'ingest s':>10}{'x':>7}"
        )
        for name, n, t_s, t_i in rows:
            print(f"{name:<16}{n:>9}{t_s:>10.3f}{t_s / ref_s:>8.2f}{t_i:>10.3f}{t_i / ref_i:>7.2f}")


if __name__ == "__main__":
    main()
