"""The report's camera images read back by frame index.

Frame ``k`` is the image message of rank ``k`` on the image topic in log-time
order, ties in file order (ingest's ``frame_index``: a stable sort of the
file-order log times). Each image here is filled with one grey value that
names the message, so a frame's pixels say which message was read.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

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
def test_streamed_frames_are_numbered_as_ingest_numbers_them(
    tmp_path: Path, log_times: list[int]
) -> None:
    path = tmp_path / "rec.mcap"
    write(path, log_times)
    n = len(log_times)
    wanted = [0, 1, 5, 17, 18, 30, 44, n - 1, n + 3]
    got = grey_values(load_images(path, TOPIC, wanted))
    assert got == {k: int(ingest_order(log_times)[k]) for k in wanted if k < n}
