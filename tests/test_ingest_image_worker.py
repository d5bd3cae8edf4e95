"""Images taken on a worker thread while the stream is read (pipeline.stages.ingest.image_worker)."""

from __future__ import annotations

import random
import threading
import time
from concurrent.futures import Future
from pathlib import Path

import pytest
from test_ingest import make

import pipeline.stages.ingest.stage as ing
import pipeline.stages.ingest.stream as stream
from pipeline.errors import BadInput
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.image_worker import ImageWorker

SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "samples" / "sample_lrmate.mcap"


class _Inline:
    """An ImageWorker that decodes and takes every image at once, on the caller's thread."""

    def __init__(self, *a: object) -> None:
        pass

    def decode(self, fn, *args):  # type: ignore[no-untyped-def]
        fut: Future = Future()
        fut.set_result(fn(*args))
        return fut

    def submit(self, fn, *args):  # type: ignore[no-untyped-def]
        fn(*args)

    def drain(self) -> None:
        pass

    def __enter__(self) -> _Inline:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def test_tasks_run_in_the_order_given_off_the_caller_thread():
    rng = random.Random(3)
    done: list[int] = []
    threads: set[str] = set()

    def task(i: int) -> None:
        time.sleep(rng.uniform(0.0, 0.003))
        threads.add(threading.current_thread().name)
        done.append(i)

    with ImageWorker(depth=4) as w:
        for i in range(40):
            w.submit(task, i)
        w.drain()
    assert done == list(range(40))
    assert threading.current_thread().name not in threads


def test_an_error_is_raised_once_by_the_next_call_and_later_tasks_are_not_taken():
    done: list[int] = []

    def task(i: int) -> None:
        if i == 2:
            raise BadInput("image 2 is bad")
        done.append(i)

    with ImageWorker(depth=2) as w, pytest.raises(BadInput, match="image 2"):
        for i in range(10):
            w.submit(task, i)
        w.drain()
    assert done == [0, 1]


def test_submit_waits_when_depth_images_wait_for_the_worker():
    gate = threading.Event()
    with ImageWorker(depth=2) as w:
        w.submit(lambda: gate.wait(5.0))
        w.submit(lambda: None)
        threading.Timer(0.3, gate.set).start()
        t0 = time.perf_counter()
        w.submit(lambda: None)  # two wait already: this one waits for the first
        assert time.perf_counter() - t0 >= 0.2
        w.drain()


def test_detection_overlaps_the_reading_and_gives_the_inline_tables(monkeypatch):
    """Each image is detected off the reading thread while joint states go on being read;
    a slow detector changes neither the order nor any value of the tables."""
    frames0, dets0, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())
    events: list[tuple[str, str]] = []
    detect, take_joint = stream.detect_target, stream._take_joint_state

    def slow_detect(*a, **kw):  # type: ignore[no-untyped-def]
        events.append(("detect", threading.current_thread().name))
        time.sleep(0.004)
        out = detect(*a, **kw)
        events.append(("detected", threading.current_thread().name))
        return out

    def joint(*a, **kw):  # type: ignore[no-untyped-def]
        events.append(("joint", threading.current_thread().name))
        return take_joint(*a, **kw)

    monkeypatch.setattr(stream, "detect_target", slow_detect)
    monkeypatch.setattr(stream, "_take_joint_state", joint)
    frames, dets, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())
    assert frames.equals(frames0) and dets.equals(dets0)
    main = threading.current_thread().name
    assert {t for e, t in events if e == "detect"} - {main}
    assert all(t != main for e, t in events if e == "detect")
    # joint states read between a detection's start and its end: the two overlapped
    inside, overlapped = False, 0
    for e, _ in events:
        inside = (inside or e == "detect") and e != "detected"
        overlapped += inside and e == "joint"
    assert overlapped > 0

    monkeypatch.setattr(ing, "ImageWorker", _Inline)
    frames2, dets2, _ = ing.ingest_recording(SAMPLE, ing.IngestConfig(), DetectConfig())
    assert frames2.equals(frames0) and dets2.equals(dets0)


def test_an_image_error_wins_over_a_later_message_error(tmp_path, monkeypatch):
    """The first error in file order is the one raised, though the image's comes later."""
    p = tmp_path / "rec.mcap"
    stamps = make(p)
    where: list[str] = []
    take_image, take_joint = stream._take_image, stream._take_joint_state

    def image(path, topic, sname, menc, msg, s, *rest):  # type: ignore[no-untyped-def]
        if len(s.rows) == 1:
            where.append(threading.current_thread().name)
            time.sleep(0.2)  # the reader has gone on to the bad joint state meanwhile
            raise BadInput(f"{path}: image 1 does not decode")
        return take_image(path, topic, sname, menc, msg, s, *rest)

    def joint(path, topic, sname, msg, config, s):  # type: ignore[no-untyped-def]
        if msg.log_time > stamps[1] + 100_000_000:  # image 1 is logged 30 ms after its stamp
            raise BadInput(f"{path}: a later joint state does not decode")
        return take_joint(path, topic, sname, msg, config, s)

    monkeypatch.setattr(stream, "_take_image", image)
    monkeypatch.setattr(stream, "_take_joint_state", joint)
    with pytest.raises(BadInput, match="image 1 does not decode"):
        ing.ingest_recording(p, ing.IngestConfig(), DetectConfig())
    assert where and where[0] != threading.current_thread().name
