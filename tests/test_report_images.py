"""The report's camera images read back by frame index: through the MCAP index and streamed.

Frame ``k`` is the image message of rank ``k`` on the image topic in log-time
order, ties in file order (ingest's ``frame_index``: a stable sort of the
file-order log times). Each image here is filled with one grey value that
names the message, so a frame's pixels say which message was read. The
indexed read (:func:`pipeline.io.mcap_index.topic_messages`) must give the same
frames as the streaming pass, also when chunks overlap in time and log times
repeat, and must step aside (None) for a file whose index it cannot trust.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer

from pipeline.io.mcap_index import topic_messages
from pipeline.report.images import load_images

TOPIC = "/camera/image_raw"
H, W = 24, 32


def _image(value: int, stamp_ns: int) -> bytes:
    """A foxglove RawImage (JSON, mono8) filled with ``value``."""
    px = np.full((H, W), value, dtype=np.uint8)
    obj = {
        "timestamp": {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000},
        "frame_id": "camera",
        "width": W,
        "height": H,
        "encoding": "mono8",
        "step": W,
        "data": base64.b64encode(px.tobytes()).decode(),
    }
    return json.dumps(obj).encode()


def write(path: Path, log_times: list[int], **options: object) -> None:
    """An MCAP file: image ``i`` (grey value ``i``) at ``log_times[i]``, written in list order.

    A ``/noise`` message (another channel) follows every image, so chunks of
    ~8 kB hold a few images each and records of two channels interleave.
    """
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=8192, compression=CompressionType.ZSTD, **options)  # type: ignore[arg-type]
        w.start()
        sid = w.register_schema("foxglove.RawImage", "jsonschema", b"{}")
        cid = w.register_channel(TOPIC, "json", sid)
        noise = w.register_channel("/noise", "json", 0)
        for i, t in enumerate(log_times):
            w.add_message(cid, log_time=t, data=_image(i, t), publish_time=t, sequence=i)
            w.add_message(noise, log_time=t, data=b"{}", publish_time=t, sequence=i)
        w.finish()


def ingest_order(log_times: list[int]) -> np.ndarray:
    """Message (file position) of each frame index, as ingest numbers them."""
    return np.argsort(np.asarray(log_times, dtype=np.int64), kind="stable")


def grey_values(frames: dict) -> dict[int, int]:
    return {k: int(f.gray[0, 0]) for k, f in frames.items()}


IN_ORDER = [1_000_000 * (i + 1) for i in range(60)]
#: chunks that overlap in time, repeated log times, a late message early in the file
SHUFFLED = [((i * 37) % 60) // 2 * 1_000_000 for i in range(60)]


@pytest.mark.parametrize("log_times", [IN_ORDER, SHUFFLED], ids=["in-order", "shuffled"])
def test_indexed_read_gives_the_streamed_frames(tmp_path: Path, log_times: list[int]) -> None:
    path = tmp_path / "rec.mcap"
    write(path, log_times)
    n = len(log_times)
    found = topic_messages([path], TOPIC, range(n), n)
    assert found is not None, "the index was not used"
    wanted = [0, 1, 5, 17, 18, 30, 44, n - 1, n + 3]
    indexed = grey_values(load_images(path, TOPIC, wanted, n_images=n))
    streamed = grey_values(load_images(path, TOPIC, wanted))
    expected = {k: int(ingest_order(log_times)[k]) for k in wanted if k < n}
    assert indexed == streamed == expected


def test_the_simulated_chunks_are_several(tmp_path: Path) -> None:
    """The test files hold several chunks (~7 images each), overlapping in time when shuffled."""
    from mcap.reader import make_reader

    path = tmp_path / "rec.mcap"
    write(path, SHUFFLED)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 8
    starts = [ci.message_start_time for ci in summary.chunk_indexes]
    ends = [ci.message_end_time for ci in summary.chunk_indexes]
    assert any(s < e for s, e in zip(starts[1:], ends[:-1], strict=True))  # overlap in time
    assert len(set(SHUFFLED)) == len(SHUFFLED) // 2  # every log time twice


@pytest.mark.parametrize(
    "options",
    [{"use_chunking": False}, {"index_types": IndexType.NONE}, {"use_statistics": False}],
    ids=["no-chunks", "no-message-index", "no-statistics"],
)
def test_a_file_without_a_usable_index_is_streamed(tmp_path: Path, options: dict) -> None:
    path = tmp_path / "rec.mcap"
    write(path, SHUFFLED, **options)
    n = len(SHUFFLED)
    assert topic_messages([path], TOPIC, range(n), n) is None
    got = grey_values(load_images(path, TOPIC, [2, 40], n_images=n))
    assert got == {k: int(ingest_order(SHUFFLED)[k]) for k in (2, 40)}


def test_a_truncated_file_is_streamed(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    write(full, IN_ORDER)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size * 2 // 3])
    assert topic_messages([cut], TOPIC, [0], 60) is None
    got = grey_values(load_images(cut, TOPIC, [0, 3, 59], n_images=30))
    assert got[0] == 0 and got[3] == 3 and 59 not in got


def test_a_count_unlike_ingests_streams(tmp_path: Path) -> None:
    """A damaged chunk that streaming skips shifts the frame numbers: the index, which
    still counts its messages, must not be used (ingest's count tells)."""
    path = tmp_path / "rec.mcap"
    write(path, IN_ORDER)
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        ci = make_reader(f).get_summary().chunk_indexes[2]  # type: ignore[union-attr]
    raw = bytearray(path.read_bytes())
    mid = ci.chunk_start_offset + ci.chunk_length // 2
    raw[mid : mid + 16] = bytes(16)  # the chunk's CRC fails: a streaming pass skips it
    path.write_bytes(bytes(raw))
    streamed = grey_values(load_images(path, TOPIC, range(60)))
    n_ingest = len(streamed)  # what ingest numbered
    assert 0 < n_ingest < 60
    assert topic_messages([path], TOPIC, [0], n_ingest) is None
    assert grey_values(load_images(path, TOPIC, range(60), n_images=n_ingest)) == streamed
