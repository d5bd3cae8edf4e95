"""Images decoded ahead in a second thread (pipeline.stages.ingest.prefetch)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import pipeline.stages.ingest.stage as ing
from pipeline.io.layout import locate
from pipeline.io.mcap import IMAGE_TYPES, StreamState
from pipeline.io.recording import iter_recording
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.prefetch import decode_image, prefetch_images

SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "samples" / "sample_lrmate.mcap"


def test_messages_in_order_and_each_image_decoded_as_inline():
    state = StreamState(str(SAMPLE))
    plain = list(iter_recording(locate(str(SAMPLE)), state))
    state2 = StreamState(str(SAMPLE))

    def wants(m):
        _, sname, menc = state2.topic_type(m.channel_id)
        return (sname, menc) if sname in IMAGE_TYPES else None

    got = list(prefetch_images(iter_recording(locate(str(SAMPLE)), state2), wants))
    assert [m.data for m, _ in got] == [m.data for m in plain]
    n = 0
    for m, fut in got:
        if fut is None:
            continue
        n += 1
        _, sname, menc = state2.topic_type(m.channel_id)
        enc, grey, e1, e2 = fut.result()
        ref = decode_image(sname, menc, m.data)
        assert e1 is None and e2 is None and np.array_equal(grey, ref[1])
    assert n == 75


def test_a_read_error_comes_after_the_messages_read_before_it():
    def stream():
        for i in range(5):
            yield SimpleNamespace(data=b"x", i=i)
        raise OSError("chunk 3: bad CRC")

    taken = []
    with pytest.raises(OSError, match="bad CRC"):
        for m, _ in prefetch_images(stream(), lambda m: None):
            taken.append(m.i)
    assert taken == [0, 1, 2, 3, 4]


def test_bad_bytes_fail_when_their_message_is_taken():
    msgs = [SimpleNamespace(data=b"\x00\x01\x00\x00\x01"), SimpleNamespace(data=b"")]
    got = list(prefetch_images(iter(msgs), lambda m: ("sensor_msgs/msg/Image", "cdr")))
    for _, fut in got:
        enc, grey, e1, _ = fut.result()
        assert enc is None and grey is None and e1 is not None


def test_ingest_tables_identical_with_and_without_the_read_ahead(monkeypatch):
    frames, dets, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())

    def inline(messages, wants, **kw):
        for m in messages:
            yield m, None

    monkeypatch.setattr(ing, "prefetch_images", inline)
    frames2, dets2, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())
    assert frames.equals(frames2) and dets.equals(dets2)
