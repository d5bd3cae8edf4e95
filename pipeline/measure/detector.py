"""vtcal's own target detector as the touch-up loop's default :data:`~pipeline.measure.loop.Detector`.

The frame is reduced to grey exactly as ingest reduces a recorded image
(:func:`pipeline.io_mcap.image_to_gray`: BT.601 weights for colour), then
:func:`pipeline.stages.detect.detect_target` fits the target's ellipse. The
loop thus drives the target to the designated values as the pipeline will
later measure them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pipeline.io_mcap import EncodedImage, image_to_gray
from pipeline.measure.loop import Detection, Detector
from pipeline.measure.protocols import Frame
from pipeline.stages.detect import DetectConfig, detect_target


def frame_to_grey(frame: Frame) -> np.ndarray:
    """Grey ``(H, W)`` image of ``frame`` (mono8 / mono16 as they are, rgb8 / bgr8 by BT.601)."""
    img = np.ascontiguousarray(frame.image)
    h, w = img.shape[:2]
    enc = EncodedImage(
        stamp_ns=int(frame.stamp_ns),
        kind="raw",
        encoding=frame.encoding,
        height=h,
        width=w,
        step=img.strides[0],
        bigendian=img.dtype.byteorder == ">",
        data=img.tobytes(),
    )
    return image_to_gray(enc)


def vtcal_detector(
    polarity: str, config: DetectConfig | None = None, size_px: float | None = None
) -> Detector:
    """A :data:`Detector` running vtcal's detector with ``polarity``.

    Parameters
    ----------
    polarity : str
        ``dark_on_light`` or ``light_on_dark``.
    config : DetectConfig, optional
        Detection settings (the polarity is set from ``polarity``).
    size_px : float, optional
        Expected long axis before the first detection (the designated ``s0``);
        afterwards the last detection's. With the loop's expected centre it picks
        the target among competing blobs.

    Returns
    -------
    ``detect(frame, expected_uv) -> (u, v, s) | None``: None when no target is
    found. A detection cut by the border is returned as found; the loop's
    geometric border rule gives up on it.
    """
    cfg = dataclasses.replace(config or DetectConfig(), polarity=polarity)
    if cfg.response == "auto":
        cfg = dataclasses.replace(cfg, response="linear")
    last_size = [size_px]

    def detect(frame: Frame, expected_uv: tuple[float, float] | None) -> Detection:
        grey = frame_to_grey(frame)
        s = last_size[0]
        expected = None if expected_uv is None or s is None else (*expected_uv, s)
        r = detect_target(grey, cfg, expected)
        if not r["found"]:
            return None
        last_size[0] = float(r["s"])
        return (float(r["u"]), float(r["v"]), float(r["s"]))

    return detect
