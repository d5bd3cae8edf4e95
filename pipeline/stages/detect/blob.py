"""Coarse blob search of the detector (step 1 of :mod:`pipeline.stages.detect.detector`).

On a ``k``-times subsampled copy (:func:`coarse_image`): plate level = median,
the target's extreme level = min (dark on light) or max; the caller thresholds
halfway. Connected components of target size are the candidates
(:func:`pick_blob`): the blob is picked by size and, when an expected
``(u, v, s)`` is given, by distance to it; competing blobs are counted and an
ambiguity ratio reported. :func:`blob_window` cuts the full-resolution window
around the blob and the masks of the pixels well inside it and well outside it,
to which the sub-pixel stage fits its level surfaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

try:  # the compiled coarse pass (numba)
    from pipeline.stages.detect import _jit
except ImportError:  # pragma: no cover - numba missing: NumPy path
    _jit = None  # type: ignore[assignment]

_KER3 = np.ones((3, 3), np.uint8)  # 3x3 structuring element of the core / plate masks


def coarse_image(img: np.ndarray, k: int, compiled: bool) -> tuple[np.ndarray, Any, Any, Any]:
    """The ``k``-times subsampled image, its plate level (median) and its extremes.

    Plain subsampling: the coarse search only needs the blob, and a threshold
    halfway between the levels is many noise sigmas from both. ``compiled``: one
    compiled pass for uint8 images when numba is installed. Returns
    ``(small, bg, lo, hi)``.
    """
    H, W = img.shape
    Ws, Hs = W // k, H // k
    if img.dtype == np.uint8 and compiled and _jit is not None and Hs > 0 and Ws > 0:
        # one compiled pass: the same subsample, median and extremes
        small, bg, lo, hi = _jit.coarse_uint8(img, k)
    else:
        small = np.ascontiguousarray(img[k // 2 : Hs * k : k, k // 2 : Ws * k : k])
        sub = small[::2, ::2].ravel()
        bg = float(np.partition(sub, sub.size // 2)[sub.size // 2])
        lo, hi, _, _ = cv2.minMaxLoc(small)
    return small, bg, lo, hi


@dataclass
class Blob:
    """The blob the coarse search picked, and how it competed with the others.

    Attributes
    ----------
    box : its bounding box ``(x0, y0, w, h)`` on the coarse grid
    contour : (N, 2) its outline, full-resolution px
    n_blobs : blobs of target size in the image
    border : the box touches the coarse image's border
    ambiguity, ambiguous : area ratio of the runner-up, and whether it competes
    """

    box: tuple[int, int, int, int]
    contour: np.ndarray
    n_blobs: int
    border: bool
    ambiguity: float
    ambiguous: bool


def pick_blob(
    small: np.ndarray,
    thr: float,
    dark: bool,
    k: int,
    shape: tuple[int, int],
    expected: tuple[float, float, float] | None,
    *,
    min_area_px: float,
    max_area_frac: float,
    ambiguity_ratio: float,
) -> Blob | None:
    """The target's blob: the largest or, given ``expected`` ``(u, v, s)``, the closest.

    Parameters
    ----------
    small : the coarse image (:func:`coarse_image`), ``k`` times subsampled
    thr : the threshold halfway between plate and target levels
    dark : the target is darker than the plate
    k : the subsampling factor
    shape : ``(H, W)`` of the full-resolution image
    expected : where the target is expected, or None
    min_area_px, max_area_frac, ambiguity_ratio : the
        :class:`~pipeline.stages.detect.detector.DetectConfig` settings of the same names

    Returns
    -------
    Blob or None
        The chosen connected component of the thresholded image among those of
        target size (None when there is none), with how many there were and how
        closely the runner-up competes.
    """
    H, W = shape
    Ws, Hs = W // k, H // k
    mask = (small < thr) if dark else (small > thr)
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    kk = float(k * k)
    cand = []
    for c in contours:
        x0c, y0c, wc, hc = cv2.boundingRect(c)
        # blob area ~ polygon area + half the boundary (pixel-centre contour)
        area = (cv2.contourArea(c) + 0.5 * len(c) + 1.0) * kk
        if area < min_area_px or area > max_area_frac * H * W:
            continue
        m = cv2.moments(c)
        if m["m00"] > 0:
            cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
        else:
            cx, cy = x0c + 0.5 * (wc - 1), y0c + 0.5 * (hc - 1)
        cand.append((area, cx * k + k // 2, cy * k + k // 2, (x0c, y0c, wc, hc), c))
    if not cand:
        return None
    compact = [_solidity(c[4]) >= MIN_SOLIDITY for c in cand]
    # a handful of candidates: plain floats (NumPy calls on 1-element arrays cost more)
    areas = [c[0] for c in cand]
    use_exp = expected is not None and all(math.isfinite(float(e)) for e in expected)
    score: list[float] = []
    if use_exp:
        assert expected is not None
        eu, ev, es = expected
        es = max(float(es), 1.0)
        score = [
            math.hypot(c[1] - eu, c[2] - ev) / es
            + abs(math.log(math.sqrt(c[0] * 4 / math.pi) / es))
            for c in cand
        ]
        order = sorted(range(len(cand)), key=score.__getitem__)
    else:
        # the largest round blob: a target is a filled ellipse, the dark crescent a
        # lamp's beam edge leaves at a plate's far side is not (it was taken for the
        # target when larger: every capture of a target near it lost)
        order = sorted(range(len(cand)), key=lambda i: (not compact[i], -areas[i]))
    best = order[0]
    ambiguity = 0.0
    ambiguous = False
    rivals = [i for i in order[1:] if compact[i] or not compact[best]]
    if rivals:
        second = rivals[0]
        ambiguity = float(min(areas[second], areas[best]) / max(areas[best], areas[second]))
        if use_exp:
            ambiguous = bool(score[second] < score[best] + 0.5 and ambiguity > ambiguity_ratio)
        else:
            ambiguous = ambiguity > ambiguity_ratio
    x0s, y0s, ws, hs = cand[best][3]
    return Blob(
        box=(x0s, y0s, ws, hs),
        contour=cand[best][4].reshape(-1, 2).astype(np.float64) * k + k // 2,
        n_blobs=len(cand),
        border=bool(x0s == 0 or y0s == 0 or x0s + ws >= Ws or y0s + hs >= Hs),
        ambiguity=ambiguity,
        ambiguous=ambiguous,
    )


#: a blob whose area is below this share of its convex hull's is not taken for the target
#: while a rounder one of target size is there (an ellipse: 1; a half-moon: ~0.6)
MIN_SOLIDITY = 0.8


def _solidity(contour: np.ndarray) -> float:
    """Area of a coarse contour over that of its convex hull (each + half its boundary)."""
    hull = cv2.convexHull(contour)
    a = cv2.contourArea(contour) + 0.5 * len(contour) + 1.0
    h = cv2.contourArea(hull) + 0.5 * cv2.arcLength(hull, True) + 1.0
    return float(a / h)


def blob_window(
    img: np.ndarray, blob: Blob, thr: float, dark: bool, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int, int] | None:
    """The full-resolution window around the blob (6 px margin) and its pixel masks.

    Returns ``(roi, core, outer, u0, v0, u1, v1)``: ``core`` the pixels well inside
    the blob (the threshold mask eroded twice; the mask itself when that is empty),
    ``outer`` those well outside it (not in the mask dilated three times), the window
    ``img[v0:v1, u0:u1]``; None when either set is (nearly) empty.
    """
    H, W = img.shape
    x0s, y0s, ws, hs = blob.box
    mg = 6
    u0 = max(x0s * k - mg, 0)
    v0 = max(y0s * k - mg, 0)
    u1 = min((x0s + ws) * k + mg, W)
    v1 = min((y0s + hs) * k + mg, H)
    img_roi = img[v0:v1, u0:u1]
    # integer grey levels and the half-integer threshold compare exactly in any dtype
    inside = ((img_roi < thr) if dark else (img_roi > thr)).view(np.uint8)
    core = cv2.erode(inside, _KER3, iterations=2)
    outer = cv2.dilate(inside, _KER3, iterations=3) == 0
    core_b = core.astype(bool) if core.any() else inside.astype(bool)
    if not core_b.any() or int(outer.sum()) < 6:
        return None
    return img_roi, core_b, outer, u0, v0, u1, v1


def auto_polarity(bg: float, lo: float, hi: float) -> str:
    """The polarity of a coarse image: dark targets when its plate level (median) is nearer
    its bright extreme than its dark one."""
    return "dark_on_light" if (bg - lo) >= (hi - bg) else "light_on_dark"


def image_polarity(image: np.ndarray, downsample: int = 4, compiled: bool = True) -> str:
    """The polarity automatic detection takes for this grey image (uint8 / uint16 / float32),
    from its ``downsample``-times coarse image (:func:`coarse_image`)."""
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    _, bg, lo, hi = coarse_image(img, max(int(downsample), 1), compiled)
    return auto_polarity(float(bg), float(lo), float(hi))
