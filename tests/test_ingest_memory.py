"""Ingest keeps one image at a time: its memory does not grow with the number of images.

Two simulated recordings of the same cell (320 x 256 PNG), one with 4x the
measuring poses of the other (51 and 141 images with seed 3), are ingested
under :mod:`tracemalloc` (numpy's buffers are traced too). The peak of Python-level allocations during ingest
(decoded images, detector work arrays, the per-image result rows, the tables
built at the end, and the small crops the flat field keeps and its sums) must
stay within 1.1x: measured 5.30 and 5.28 MB (stop 30; the flat field's first
version cached every crop's edge model, up to 300, and gave 10.8 MB on the
larger one). Both
recordings are written in 256 kB chunks, so that both span many (a chunk is
decompressed whole: its size bounds, not the file's, what is held). Ingest
that kept the images would grow with them (2.8x); joint states kept as a list
of small arrays, as before ``RowBuffer``, gave 5.52 and 6.43 MB (1.17x).
``benchmarks/bench_memory.py`` measures the peak RSS on a 2 GB recording.
"""

from __future__ import annotations

import dataclasses
import tracemalloc
from pathlib import Path

import pytest

from pipeline.sim.scenario import load_scenario
from pipeline.sim.simulator import write_recording
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording

CELL = """\
name = "memory_small"
[robot]
name = "lrmate"
[camera]
width = 320
height = 256
[targets]
count = 3
[poses]
per_target = 2
[timing]
chunk_size = 262144
"""


def _ingest_peak(path: Path) -> tuple[int, int]:
    """(images, peak traced bytes) of one ingest; the first run warms every import."""
    tracemalloc.start()
    try:
        frames, _, _ = ingest_recording(path, IngestConfig(), DetectConfig())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return len(frames), peak


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    d = tmp_path_factory.mktemp("ingest_memory")
    (d / "cell.toml").write_text(CELL)
    sc = load_scenario(d / "cell.toml")
    out = {}
    for per_target in (2, 8):
        scn = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, per_target=per_target))
        out[per_target] = d / f"cell_{per_target}.mcap"
        write_recording(scn, 3, out[per_target])
    return out


def test_ingest_peak_memory_does_not_grow_with_images(recordings: dict[int, Path]) -> None:
    ingest_recording(recordings[2], IngestConfig(), DetectConfig())  # imports, compiled code
    n_small, peak_small = _ingest_peak(recordings[2])
    n_large, peak_large = _ingest_peak(recordings[8])
    assert n_large >= 2.5 * n_small
    assert peak_large <= 1.1 * peak_small, (n_small, peak_small, n_large, peak_large)


def test_row_buffer_equals_the_rows_stacked() -> None:
    """Across several doublings of its capacity, the buffer holds exactly the rows given."""
    import numpy as np

    from pipeline.stages.ingest.row_buffer import RowBuffer

    rng = np.random.default_rng(5)
    rows = rng.normal(size=(1000, 6))
    stamps = rng.integers(0, 2**62, size=1000)
    buf, sbuf = RowBuffer(6, capacity=3), RowBuffer(0, np.int64, capacity=3)
    for r, s in zip(rows, stamps, strict=True):
        buf.append(r)
        sbuf.append(int(s))
    assert len(buf) == 1000 and buf.array().shape == (1000, 6)
    assert np.array_equal(buf.array(), np.asarray(list(rows)))
    assert sbuf.array().dtype == np.int64 and np.array_equal(sbuf.array(), stamps)
