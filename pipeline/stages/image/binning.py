"""Large images whose target edges are too wide for the detector: binned before detection.

The detector (:mod:`pipeline.stages.detect.detector`) fits an edge a pixel or two wide
(``DetectConfig.max_edge_sigma_px``). An image of many megapixels that
resolves the target's edge over many pixels (an over-resolving lens, a
defocus, an image upscaled by the camera driver) gives edges it cannot fit:
``incomplete``/``fit_failed`` on every image. Averaging ``b x b`` blocks
(binning) narrows the edge ``b`` times and keeps every photon, so the same
image is read at the scale the detector fits; the detections are mapped back
to full-resolution pixels:

``u = b u_b + (b - 1) / 2`` (block ``j`` covers pixels ``jb .. jb + b - 1``),
likewise ``v``; lengths (``s``, ``s_minor``, the clip correction) times ``b``;
``s_inv`` divided by ``b``. The fit residual and edge width stay in binned
pixels: they judge the fit, against thresholds in the detector's pixels.

The factor is chosen once per recording, from its first image
(:func:`choose_binning`): 1 when the full-resolution detection is clean, else
the smallest power of two whose binned detection is.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from pipeline.stages.detect.detector import DetectConfig, detect_target

#: binning factors tried, in order, for an image the detector does not read cleanly
FACTORS = (2, 4, 8, 16)
#: a binned image keeps at least this many pixels on its short side
MIN_BINNED_SIDE = 48
#: detection keys that are lengths in image pixels (times ``b``); the fit's quality figures
#: (``residual_px``, ``edge_sigma_px``) stay in the pixels the detector saw, where its
#: thresholds (and the outlier rules') hold
LENGTHS = ("s", "s_minor", "clip_correction_px")


def bin_image(grey: np.ndarray, b: int) -> np.ndarray:
    """The ``b x b`` block means of a grey image, as ``uint16`` (8-bit grey times 257).

    The image is cropped to whole blocks (at most ``b - 1`` rows and columns
    at the bottom and right). 8-bit data are scaled to the 16-bit range first,
    so the mean keeps its fractions and the response curve and clip level
    keep their meaning (255 -> 65535).

    Parameters
    ----------
    grey : (H, W) uint8 or uint16
    b : block side, >= 1

    Returns
    -------
    (H // b, W // b) uint16 (``grey`` itself when ``b`` is 1)
    """
    if b <= 1:
        return grey
    H, W = grey.shape
    g = grey[: H - H % b, : W - W % b].astype(np.float32)
    if grey.dtype == np.uint8:
        g *= 257.0
    out = cv2.resize(g, (W // b, H // b), interpolation=cv2.INTER_AREA)
    return np.rint(np.clip(out, 0, 65535)).astype(np.uint16)


def scaled_position(x: float, b: float) -> float:
    """A pixel coordinate of an image scaled down ``b`` times in the original's pixels,
    ``b x + (b - 1) / 2`` (pixel ``j`` covers ``j b .. j b + b - 1``; any ``b > 0``: below 1
    it maps the other way)."""
    return b * float(x) + 0.5 * (b - 1)


def unbin(det: dict[str, Any], b: float) -> dict[str, Any]:
    """A detection on a ``b``-binned image in full-resolution pixels (see the module doc;
    ``b`` need not be whole: an image scaled down by any factor maps the same way)."""
    if b <= 1:
        return det
    out = dict(det)
    for k in ("u", "v"):
        out[k] = scaled_position(det[k], b)
    for k in LENGTHS:
        out[k] = b * float(det[k])
    out["s_inv"] = float(det["s_inv"]) / b
    return out


def _clean(det: dict[str, Any]) -> bool:
    return bool(det["found"] and det["quality_ok"])


def choose_binning(grey: np.ndarray, config: DetectConfig) -> tuple[int, str]:
    """The binning factor for a recording from one of its images, and why (one phrase).

    1 when the full-resolution detection is clean (found, quality ok) or no
    binned one is; else the smallest factor of :data:`FACTORS` (keeping
    :data:`MIN_BINNED_SIDE` pixels) whose binned image gives a clean detection.
    """
    det = detect_target(grey, config)
    if _clean(det):
        return 1, ""
    for b in FACTORS:
        if min(grey.shape) // b < MIN_BINNED_SIDE:
            break
        det_b = detect_target(bin_image(grey, b), config)
        if _clean(det_b):
            H, W = grey.shape
            return b, (
                f"{b} ({W}x{H} images: the target's edge is {b * det_b['edge_sigma_px']:.1f} px "
                f"wide (sigma), beyond the detector's {config.max_edge_sigma_px:g} px at full "
                f"resolution ({det['reason'] or 'not found'}); detected on {b}x{b} block means, "
                "positions mapped back to full-resolution pixels)"
            )
    return 1, ""
