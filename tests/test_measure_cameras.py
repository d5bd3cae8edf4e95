"""Camera adapters: a folder an external tool writes into, and an OpenCV capture source."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.live.cameras import FolderCamera, OpenCVCamera, stamp_from_name
from pipeline.live.protocols import Camera, MeasureFault


def _img(k: int, dtype: type = np.uint8) -> np.ndarray:
    a = (np.arange(40 * 50).reshape(40, 50) * (k + 3)) % 251
    return a.astype(dtype) * (257 if dtype == np.uint16 else 1)


def test_folder_camera_returns_the_next_new_file_and_its_stamp(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "old_1700000000000000001.png"), _img(0))  # before: stale
    cam = FolderCamera(tmp_path, timeout_s=5.0)
    assert isinstance(cam, Camera)
    stamp = 1_700_000_123_456_789_012

    def drop() -> None:
        time.sleep(0.15)
        tmp = tmp_path / "tmp.partial"
        cv2.imwrite(str(tmp) + ".png", _img(1, np.uint16))
        (tmp_path / "tmp.partial.png").rename(tmp_path / f"cap_{stamp}.png")

    t = threading.Thread(target=drop)
    t.start()
    f = cam.capture()
    t.join()
    assert f.stamp_ns == stamp and f.encoding == "mono16"
    assert np.array_equal(f.image, _img(1, np.uint16))


def test_folder_camera_skips_files_that_arrived_between_captures(tmp_path: Path) -> None:
    cam = FolderCamera(tmp_path, timeout_s=5.0)
    cv2.imwrite(str(tmp_path / "a.png"), _img(1))  # arrives while no capture waits: stale

    def drop() -> None:
        time.sleep(0.1)
        cv2.imwrite(str(tmp_path / "b.png"), _img(2))

    t = threading.Thread(target=drop)
    t.start()
    f = cam.capture()
    t.join()
    assert np.array_equal(f.image, _img(2)) and f.encoding == "mono8"
    assert f.stamp_ns == (tmp_path / "b.png").stat().st_mtime_ns  # no stamp in the name


def test_folder_camera_times_out(tmp_path: Path) -> None:
    cam = FolderCamera(tmp_path, timeout_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(MeasureFault) as e:
        cam.capture()
    assert e.value.kind == "camera_timeout" and "0.2 s" in str(e.value)
    assert 0.2 <= time.monotonic() - t0 < 1.0


def test_stamp_from_name() -> None:
    assert stamp_from_name(Path("x_1700000000123456789.png")) == 1700000000123456789
    assert stamp_from_name(Path("frame_0042.png")) is None


def test_opencv_camera_reads_a_video_file_then_times_out(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG/AVI")
    frames = [np.full((48, 64, 3), 40 * k, np.uint8) for k in range(3)]
    for fr in frames:
        w.write(fr)
    w.release()
    cam = OpenCVCamera(str(path), timeout_s=2.0)
    before = time.time_ns()
    got = [cam.capture() for _ in range(3)]
    for fr, g in zip(frames, got, strict=True):
        assert g.encoding == "bgr8" and g.image.shape == (48, 64, 3)
        assert abs(float(g.image.mean()) - float(fr.mean())) < 3.0  # JPEG-compressed
        assert before <= g.stamp_ns <= time.time_ns()
    with pytest.raises(MeasureFault) as e:
        cam.capture()  # the file is over
    assert e.value.kind == "camera_timeout"
    cam.close()


def test_opencv_camera_that_cannot_open_is_a_connection_fault(tmp_path: Path) -> None:
    with pytest.raises(MeasureFault) as e:
        OpenCVCamera(str(tmp_path / "missing.avi"))
    assert e.value.kind == "connection"
