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


def _srgb_disc(u: float, v: float, d: float) -> np.ndarray:
    """The disc of :func:`_disc` as an sRGB camera encodes it (blurred edge, then the curve)."""
    import cv2

    lin = cv2.GaussianBlur(_disc(u, v, d) / 255.0, (0, 0), 1.0)
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    return np.round(255.0 * enc).astype(np.uint8)


def test_a_resumed_measurement_keeps_the_response_it_learned() -> None:
    """An undeclared response is estimated from the first clean captures (detected on raw
    grey meanwhile); a resumed session takes the estimate from the progress state instead
    of detecting its next captures on raw grey again, and a declared one stays."""
    frames = [Frame(_srgb_disc(80.0 + 0.3 * k, 60.0 - 0.2 * k, 40.0), k, "mono8") for k in range(7)]
    first = vtcal_detector("dark_on_light", size_px=40.0, response="auto")
    raw = first(frames[0], (80.0, 60.0))
    assert first.source == "pending" and first.learned() == {}
    for f in frames[1:]:
        first(f, (80.0, 60.0))
    assert first.source == "estimated" and first.learned() == {"camera_response": "srgb"}

    said: list[str] = []
    again = vtcal_detector("dark_on_light", size_px=40.0, response="auto", say=said.append)
    again.resume(first.learned())
    assert again.source == "estimated" and again.response == "srgb"
    assert "before the interruption" in said[0]
    det = again(frames[0], (80.0, 60.0))
    assert det is not None and raw is not None
    # the same capture read with the curve, not on raw grey: the size the loop stops on
    assert det[2] == pytest.approx(40.0, abs=0.05) and abs(raw[2] - 40.0) > 0.2
    assert det == first(frames[0], (80.0, 60.0))

    declared = vtcal_detector("dark_on_light", response="linear")
    declared.resume({"camera_response": "srgb"})
    assert declared.source == "declared" and declared.response == "linear"
    assert declared.learned() == {}
