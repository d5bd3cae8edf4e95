"""Camera adapters: an OpenCV ``VideoCapture`` source and a folder an external tool writes into.

Both implement :class:`~pipeline.live.protocols.Camera` and stamp images
with the host clock (``time.time_ns``), the clock the TCP robot's poller
stamps joint states with (docs/measure.md, "Clocks").

- :class:`OpenCVCamera`: a device index (``opencv:0``), a stream URL or a video
  file. Stamp: the middle of the ``read`` call. A read that does not return
  within ``timeout_s`` or returns no image is ``camera_timeout``.
- :class:`FolderCamera`: a camera with its own acquisition tool that saves
  image files into a folder. ``capture`` returns the first file that appears
  after the call (older files are stale: taken before the arm settled) once
  its size stopped changing. Stamp: a run of 16 to 19 digits in the file name,
  read as nanoseconds since the epoch (``img_1700000000123456789.png``), else
  the file's modification time.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipeline.live.protocols import Frame, MeasureFault

#: file suffixes the folder camera reads
IMAGE_SUFFIXES = (".png", ".pgm", ".ppm", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
_STAMP_RE = re.compile(r"(?<!\d)(\d{16,19})(?!\d)")


def frame_of(image: np.ndarray, stamp_ns: int) -> Frame:
    """A :class:`Frame` of an OpenCV image: grey -> mono8/mono16, colour -> bgr8 (alpha dropped)."""
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        image = np.ascontiguousarray(image[:, :, :3])
        if image.dtype != np.uint8:
            raise MeasureFault("connection", f"colour image of type {image.dtype}: expected 8 bit")
        return Frame(image, stamp_ns, "bgr8")
    if image.dtype == np.uint16:
        return Frame(image, stamp_ns, "mono16")
    if image.dtype != np.uint8:
        raise MeasureFault("connection", f"grey image of type {image.dtype}: expected 8 or 16 bit")
    return Frame(image, stamp_ns, "mono8")


class OpenCVCamera:
    """A ``cv2.VideoCapture`` source.

    Parameters
    ----------
    source : int or str
        Device index, stream URL or video file.
    timeout_s : float
        Longest a capture may take.
    discard : int
        Frames grabbed and dropped before each capture (a live device buffers a
        few, taken while the arm was still moving); 0 for a file.
    """

    def __init__(self, source: int | str, timeout_s: float = 2.0, discard: int = 0) -> None:
        self.source = source
        self.timeout_s = timeout_s
        self.discard = discard
        self._cap = cv2.VideoCapture(source)
        if not self._cap.isOpened():
            raise MeasureFault("connection", f"opencv:{source}: cannot open the capture source")

    def _read(self, out: list[Any]) -> None:
        for _ in range(self.discard):
            self._cap.grab()
        t0 = time.time_ns()
        ok, img = self._cap.read()
        out.append((ok, img, (t0 + time.time_ns()) // 2))

    def capture(self) -> Frame:
        out: list[Any] = []
        worker = threading.Thread(target=self._read, args=(out,), daemon=True)
        worker.start()
        worker.join(self.timeout_s)
        if not out:
            raise MeasureFault(
                "camera_timeout", f"opencv:{self.source}: no image within {self.timeout_s:g} s"
            )
        ok, img, stamp = out[0]
        if not ok or img is None:
            raise MeasureFault("camera_timeout", f"opencv:{self.source}: the source gave no image")
        return frame_of(img, int(stamp))

    def close(self) -> None:
        self._cap.release()


def stamp_from_name(path: Path) -> int | None:
    """Nanoseconds since the epoch named in ``path``'s file name (16-19 digits), or None."""
    m = _STAMP_RE.search(path.stem)
    return int(m.group(1)) if m else None


class FolderCamera:
    """Images an external acquisition tool saves into ``folder``.

    Parameters
    ----------
    folder : where the files appear
    timeout_s : longest a capture waits for a new file
    poll_s : how often the folder is listed
    """

    def __init__(self, folder: str | Path, timeout_s: float = 10.0, poll_s: float = 0.02) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise MeasureFault("connection", f"folder:{self.folder}: no such folder")
        self.timeout_s = timeout_s
        self.poll_s = poll_s
        self._seen = set(self._listing())

    def _listing(self) -> list[Path]:
        return [p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]

    def capture(self) -> Frame:
        self._seen |= set(self._listing())  # anything already there is stale
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            new = sorted(set(self._listing()) - self._seen, key=lambda p: p.stat().st_mtime_ns)
            if new:
                path = new[0]
                img = self._read_settled(path, deadline)
                if img is not None:
                    self._seen |= set(new)
                    stamp = stamp_from_name(path)
                    return frame_of(img, stamp if stamp is not None else path.stat().st_mtime_ns)
            time.sleep(self.poll_s)
        raise MeasureFault(
            "camera_timeout", f"folder:{self.folder}: no new image within {self.timeout_s:g} s"
        )

    def _read_settled(self, path: Path, deadline: float) -> np.ndarray | None:
        """The image once its size stopped changing and it decodes; None at the deadline."""
        size = -1
        while time.monotonic() < deadline:
            now = path.stat().st_size
            if now == size and now > 0:
                img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                if img is not None:
                    return np.asarray(img)
            size = now
            time.sleep(self.poll_s)
        return None

    def close(self) -> None:
        pass
