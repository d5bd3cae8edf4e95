"""vtcal's own target detector as the touch-up loop's default :data:`~pipeline.live.loop.Detector`.

The frame is reduced to grey exactly as ingest reduces a recorded image
(:func:`pipeline.io.mcap.image_to_gray`: BT.601 weights for colour), then
:func:`pipeline.stages.detect.detector.detect_target` fits the target's ellipse on grey
levels linearised by the camera response, declared or estimated as ingest
does (:class:`LiveDetector`). The loop thus drives the target to the
designated values as the pipeline will later measure them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from pipeline.io.mcap import EncodedImage, image_to_gray
from pipeline.live.loop import Detection
from pipeline.live.protocols import Frame
from pipeline.stages.detect.detector import DetectConfig, detect_target
from pipeline.stages.image.response_estimate import ResponseEstimate, estimate_response
from pipeline.stages.response.curve import Response, parse_response


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


#: clean captures (target found) the live loop estimates an undeclared response from: the
#: seven probing captures of the first touch-up, so its loop proper already uses the estimate
ESTIMATE_IMAGES = 7


class LiveDetector:
    """vtcal's detector for the live loop, on grey levels linearised as ingest linearises them.

    The camera response (:mod:`pipeline.stages.response.curve`) is applied by
    :func:`pipeline.stages.detect.detector.detect_target` itself (``DetectConfig.response``,
    the code path of offline detection). A declared response is used from the
    first capture. An undeclared one (``auto``) is estimated by the offline
    estimator (:func:`pipeline.stages.image.response_estimate.estimate_response`) from
    the first :data:`ESTIMATE_IMAGES` captures in which the target was found,
    detected meanwhile on raw grey (linear); ``say`` is told the outcome in one
    line. Called as a :data:`~pipeline.live.loop.Detector`.

    Attributes
    ----------
    config : DetectConfig
        The settings the next capture is detected with (its ``response`` a curve
        once known, ``linear`` while an estimate is pending).
    source : str
        ``declared``, ``estimated`` or ``pending`` (estimate not made yet).
    estimate : ResponseEstimate or None
        The estimate, when one was made.
    """

    def __init__(
        self,
        polarity: str,
        config: DetectConfig | None = None,
        size_px: float | None = None,
        response: str | None = None,
        say: Callable[[str], None] | None = None,
        estimate_images: int = ESTIMATE_IMAGES,
    ) -> None:
        cfg = dataclasses.replace(config or DetectConfig(), polarity=polarity)
        # ValueError on a bad spec: the caller words it
        fixed = cfg.response if response is None else parse_response(response)
        self.source = "declared" if fixed is not None else "pending"
        self.config = dataclasses.replace(cfg, response=fixed or Response("linear"))
        self.estimate: ResponseEstimate | None = None
        self._say = say
        self._n = max(int(estimate_images), 1)
        self._held: list[np.ndarray] = []
        self._last_size = size_px

    @property
    def response(self) -> str:
        """The spec of the response the detector linearises with now."""
        r = self.config.response
        return r.spec if r is not None else "linear"

    def __call__(self, frame: Frame, expected_uv: tuple[float, float] | None) -> Detection:
        grey = frame_to_grey(frame)
        s = self._last_size
        expected = None if expected_uv is None or s is None else (*expected_uv, s)
        r = detect_target(grey, self.config, expected)
        if not r["found"]:
            return None
        if self.source == "pending":
            self._held.append(grey)
            if len(self._held) >= self._n:
                self._estimate()
                r = detect_target(grey, self.config, expected)
                if not r["found"]:
                    return None
        self._last_size = float(r["s"])
        return (float(r["u"]), float(r["v"]), float(r["s"]))

    def learned(self) -> dict[str, str]:
        """What a resumed measurement keeps: the response estimated (empty while pending or
        when declared, which the cell's ``META?`` or ``--set`` gives again)."""
        if self.source != "estimated":
            return {}
        return {"camera_response": self.response}

    def resume(self, learned: Mapping[str, Any]) -> None:
        """Take the response an earlier session of the same recording estimated.

        A resumed measurement must not detect its next captures on raw grey again while
        it re-learns a curve it already knew (its loop would stop at another size than
        before the interruption); a declared response stays as declared.
        """
        spec = learned.get("camera_response")
        if self.source != "pending" or not spec:
            return
        fixed = parse_response(str(spec))
        if fixed is None:
            return
        self._held.clear()
        self.source = "estimated"
        self.config = dataclasses.replace(self.config, response=fixed)
        if self._say is not None:
            self._say(f"camera response {fixed.spec}: as estimated before the interruption")

    def _estimate(self) -> None:
        """Estimate the response from the held captures (the offline estimator, as it is)."""
        est = estimate_response(self._held, self.config, max_images=len(self._held))
        self._held.clear()
        self.estimate = est
        self.source = "estimated"
        self.config = dataclasses.replace(self.config, response=est.response)
        if self._say is not None:
            self._say(
                f"camera response not declared (camera_response): estimated from the first "
                f"{est.n_images} captures as {est.response.spec}: {est.note}; "
                "give --set camera_response=... if it is known"
            )


def vtcal_detector(
    polarity: str,
    config: DetectConfig | None = None,
    size_px: float | None = None,
    response: str | None = None,
    say: Callable[[str], None] | None = None,
) -> LiveDetector:
    """A :data:`Detector` running vtcal's detector with ``polarity`` (:class:`LiveDetector`).

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
    response : str, optional
        The camera response (``linear``, ``srgb``, ``gamma:G``, ``table:...``, or
        ``auto``: estimated from the first clean captures); default: ``config``'s
        (``auto`` unless set).
    say : callable, optional
        Told in one line what an estimate found.

    Returns
    -------
    ``detect(frame, expected_uv) -> (u, v, s) | None``: None when no target is
    found. A detection cut by the border is returned as found; the loop's
    geometric border rule gives up on it.
    """
    return LiveDetector(polarity, config, size_px, response, say)
