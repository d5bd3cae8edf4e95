"""vtcal's detector behind the loop's Detector interface (pipeline.live.detector).

A disc rendered by area coverage (16 x 16 subsamples per pixel) at a known
centre and diameter; the detector must find it in mono8, mono16, rgb8 and bgr8
frames alike, and report nothing on a blank frame.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.live.detector import frame_to_grey, vtcal_detector
from pipeline.live.protocols import Frame


def _disc(u: float, v: float, d: float, w: int = 160, h: int = 120, k: int = 16) -> np.ndarray:
    """Dark disc (grey 40) on a light plate (grey 200), area-coverage antialiased."""
    off = (np.arange(k) + 0.5) / k - 0.5
    ys = (np.arange(h)[:, None] + off[None, :]).reshape(-1)
    xs = (np.arange(w)[:, None] + off[None, :]).reshape(-1)
    inside = ((xs[None, :] - u) ** 2 + (ys[:, None] - v) ** 2) <= (0.5 * d) ** 2
    cover = inside.reshape(h, k, w, k).mean(axis=(1, 3))
    return 200.0 - 160.0 * cover


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "rgb8", "bgr8"])
def test_finds_the_disc_in_every_encoding(encoding: str) -> None:
    g = _disc(81.3, 57.8, 40.0)
    if encoding == "mono16":
        img = np.round(g * 257).astype(np.uint16)
    else:
        img = np.round(g).astype(np.uint8)
        if encoding in ("rgb8", "bgr8"):
            img = np.repeat(img[:, :, None], 3, axis=2)
    frame = Frame(img, 1, encoding)
    assert frame_to_grey(frame).shape == (120, 160)
    det = vtcal_detector("dark_on_light", size_px=40.0)(frame, (80.0, 60.0))
    assert det is not None
    assert det[0] == pytest.approx(81.3, abs=0.05) and det[1] == pytest.approx(57.8, abs=0.05)
    assert det[2] == pytest.approx(40.0, abs=0.1)


def test_nothing_on_a_blank_frame() -> None:
    frame = Frame(np.full((120, 160), 200, np.uint8), 1, "mono8")
    assert vtcal_detector("dark_on_light")(frame, None) is None


def test_light_on_dark_polarity() -> None:
    img = np.round(240.0 - _disc(70.0, 60.0, 30.0)).astype(np.uint8)
    det = vtcal_detector("light_on_dark")(Frame(img, 1, "mono8"), None)
    assert det is not None and det[0] == pytest.approx(70.0, abs=0.05)
