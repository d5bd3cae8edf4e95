"""One MCAP chunk's records by pipeline.io.mcap_chunk, against the mcap library's reader.

``chunk_records`` replaces ``mcap.stream_reader.breakup_chunk`` in vtcal's streaming
pass: it must return the same records (the library's own classes, equal field by
field) for every compression a recorder writes, and refuse the chunks the library
refuses (a failed CRC, a record running past the chunk's end).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from test_robustness_data import tiny_recording

from pipeline.io.mcap_chunk import ChunkError, chunk_records

REPO = Path(__file__).resolve().parents[1]


def chunks(path: Path) -> list[Chunk]:
    with open(path, "rb") as f:
        return [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]


@pytest.mark.parametrize(
    "compression", [CompressionType.NONE, CompressionType.ZSTD, CompressionType.LZ4]
)
def test_the_same_records_as_the_library(tmp_path: Path, compression: CompressionType) -> None:
    rec = tiny_recording(tmp_path / "r.mcap", n_img=5, compression=compression, chunk_size=6000)
    cs = chunks(rec)
    assert len(cs) >= 3
    n = 0
    for c in cs:
        want = breakup_chunk(c, validate_crc=True)
        got = chunk_records(c)
        assert got == want
        n += len(got)
    assert n > 100


def test_the_shipped_samples_read_the_same() -> None:
    for rec in (REPO / "datasets" / "samples").glob("*.mcap"):
        for c in chunks(rec)[:4]:
            assert chunk_records(c) == breakup_chunk(c, validate_crc=True)


def test_a_failed_crc_and_a_cut_record_are_refused(tmp_path: Path) -> None:
    rec = tiny_recording(tmp_path / "r.mcap", n_img=3, compression=CompressionType.NONE)
    c = chunks(rec)[0]
    flipped = bytearray(c.data)
    flipped[-5] ^= 0x5A
    with pytest.raises(ChunkError, match="CRC"):
        chunk_records(dataclasses.replace(c, data=bytes(flipped)))
    cut = dataclasses.replace(c, data=c.data[:-7], uncompressed_crc=0)
    with pytest.raises(ChunkError, match="past the chunk's end"):
        chunk_records(cut)
    with pytest.raises(ChunkError, match="compression"):
        chunk_records(dataclasses.replace(c, compression="brotli"))
