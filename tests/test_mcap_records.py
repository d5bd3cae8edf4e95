"""An MCAP file's and its chunks' records by pipeline.io.mcap_records, against the library.

``chunk_records`` and ``file_records`` replace ``mcap``'s ``breakup_chunk`` and
``StreamReader`` in vtcal's streaming pass: they must return the same records (the
library's own classes, equal field by field) for every compression a recorder
writes, refuse the chunks the library refuses (a failed CRC, a record running past
the chunk's end), and stop where the library stops in a cut file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from test_robustness_data import tiny_recording

from pipeline.io.mcap import StreamState, iter_messages
from pipeline.io.mcap_records import ChunkError, chunk_records

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


def library_pass(path: Path) -> tuple[list[Message], bool, int]:
    """Messages, truncated, bytes read to the end of the last whole record: the library's
    ``StreamReader`` (as vtcal read files before ``file_records``)."""
    out: list[Message] = []
    count = 0
    with open(path, "rb") as f:
        reader = StreamReader(f, emit_chunks=True)
        try:
            for rec in reader.records:
                if isinstance(rec, Chunk):
                    out += [r for r in breakup_chunk(rec) if isinstance(r, Message)]
                elif isinstance(rec, Message):
                    out.append(rec)
                count = f.tell()
        except Exception:  # noqa: BLE001 - the file ends inside a record
            return out, True, count
    return out, False, path.stat().st_size


@pytest.mark.parametrize("cut", [None, 0.3, 0.7, 0.999])
def test_a_pass_over_a_file_reads_what_the_library_reads(tmp_path: Path, cut: float | None):
    """Whole and cut files (a recorder killed): the same messages, the same truncation and
    the same count of bytes read to the end of the last whole record."""
    src = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
    data = src.read_bytes()
    rec = tmp_path / "r.mcap"
    rec.write_bytes(data if cut is None else data[: int(len(data) * cut)])
    state = StreamState(str(rec))
    got = list(iter_messages(rec, state))
    want, truncated, count = library_pass(rec)
    assert got == want and (cut == 0.3 or len(got) > 1000)  # 0.3 ends in the first chunk
    assert state.truncated == truncated == (cut is not None)
    assert state.bytes_read == count
