"""Images decoded on a thread of their own (pipeline.stages.ingest.prefetch, image_worker)."""

from __future__ import annotations

import threading
from concurrent.futures import Future
from pathlib import Path

import numpy as np

import pipeline.stages.ingest.stage as ing
from pipeline.io.layout import locate
from pipeline.io.mcap import IMAGE_TYPES, StreamState
from pipeline.io.recording import iter_recording
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.image_worker import ImageWorker
from pipeline.stages.ingest.prefetch import decode_image

SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "samples" / "sample_lrmate.mcap"


def test_each_image_decoded_on_the_decoding_thread_as_inline():
    state = StreamState(str(SAMPLE))
    where: list[str] = []

    def decode(sname, menc, data):  # type: ignore[no-untyped-def]
        where.append(threading.current_thread().name)
        return decode_image(sname, menc, data)

    n = 0
    with ImageWorker() as w:
        for m in iter_recording(locate(str(SAMPLE)), state):
            _, sname, menc = state.topic_type(m.channel_id)
            if sname not in IMAGE_TYPES:
                continue
            n += 1
            enc, grey, e1, e2 = w.decode(decode, sname, menc, m.data).result()
            ref = decode_image(sname, menc, m.data)
            assert e1 is None and e2 is None and np.array_equal(grey, ref[1])
    assert n == 75
    assert where and threading.current_thread().name not in where[:n]


def test_bad_bytes_keep_the_failing_step_apart():
    for data in (b"\x00\x01\x00\x00\x01", b""):
        enc, grey, e1, _ = decode_image("sensor_msgs/msg/Image", "cdr", data)
        assert enc is None and grey is None and e1 is not None


def test_ingest_tables_identical_with_and_without_decoding_ahead(monkeypatch):
    frames, dets, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())

    def inline(self, fn, *args):  # type: ignore[no-untyped-def]
        fut: Future = Future()
        fut.set_result(fn(*args))
        return fut

    monkeypatch.setattr(ImageWorker, "decode", inline)
    frames2, dets2, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())
    assert frames.equals(frames2) and dets.equals(dets2)
