"""A clipped plate: where the halfway contour lies when the brighter level is not seen.

A dark target on a plate bright enough to clip at the sensor's top code ``C``
is imaged as ``min(C, I)`` with the edge profile (distance ``d`` from the
contour, outward positive, Gaussian blur ``sigma`` including the pixel)

    I(d) = D + (P - D) Phi((d - delta) / sigma)                         (C1)

``D`` the target's level, ``P > C`` the plate's (a bright target on a dark
plate: the same with the roles swapped, the profile read inwards). The detector's halfway level is
then ``(D + C) / 2``, not ``(D + P) / 2``: its contour lies inside the true one.
It reads every long axis short by about ``2 sigma Phi^-1((P - C) / (2 (P - D)))``,
more with more blur. The error is the same for every capture, so no residual
shows it. On a simulated cell with 45 % over-exposure it was -0.33 px.

Fitting (C1) censored at ``C`` to the pixels of a band around the fitted
ellipse recovers ``D``, ``P``, ``sigma`` and the offset ``delta`` of the true
halfway contour from the measured one. The pixels below ``C`` carry the
profile's shape and the clipped ones only say ``I >= C``: the residual is
``min(C, I(d)) - g``. The long and short axes then grow by ``2 delta`` (the
contour moves along its normal). The centre does not move for a symmetric
offset. On a synthetic disc (60 px, sigma 0.8-1.5 px, 1 grey of noise), a plate
at 1.2-4 times the clip level read -0.37 to -3.7 px of long axis. After the fit
it read within 0.01 px. One exception, 0.1 px, was a 2.4x plate at sigma 0.8.
The fit is used only where it is physical: a bright level at least 2 % of the
seen contrast above the clip, and the contour moved towards the bright side. On
the real webcam photos of ``datasets/real/dots`` the fit put the paper at the
clip level and moved the contour inwards, so it changes nothing there. Those
edges are not Gaussian, and the paper is clipped at, not far above, 255.

The model assumes a response that is linear after the detector's
linearisation, and a Gaussian edge. A real lens's edge spread is only close to
Gaussian, so the correction removes most of the clipping error, not all of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from pipeline.stages.detect.ellipse_distance import approx_distance

#: the share of band pixels at the top code from which the plate counts as clipped
MIN_CLIPPED_SHARE = 0.05
#: the fitted bright level must exceed the clip by this share of the seen contrast
MIN_HIDDEN_CONTRAST = 0.02
#: fewer band pixels than this: no fit
MIN_BAND_PIXELS = 30


@dataclass(frozen=True)
class ClipFit:
    """The censored edge fit (C1): offset ``delta`` (px, outward) and its figures.

    ``plate_level`` is the bright side's level (the plate, or a bright target), and
    ``target_level`` the dark side's.
    """

    delta_px: float
    plate_level: float
    target_level: float
    sigma_px: float
    clipped_share: float
    ok: bool


def clip_level(dtype: np.dtype) -> float | None:
    """The top code of an integer image type (the level a clipped pixel sits at)."""
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return None


def _signed_distance(
    H: int, W: int, u0: float, v0: float, ellipse: tuple[float, float, float, float, float]
) -> np.ndarray:
    """(H, W) first-order signed distance (px, outward) of a window's pixels to an ellipse.

    The detector's own :func:`pipeline.stages.detect.ellipse_distance.approx_distance`, on the pixel grid.
    """

    vv, uu = np.mgrid[0:H, 0:W]
    pts = np.stack([uu.ravel() + u0, vv.ravel() + v0], axis=1).astype(np.float64)
    return np.asarray(approx_distance(pts, ellipse)).reshape(H, W)


def fit_clipped_edge(
    roi: np.ndarray,
    u0: float,
    v0: float,
    ellipse: tuple[float, float, float, float, float],
    sigma_px: float,
    clip: float,
    dark: bool | None = True,
) -> ClipFit:
    """Fit (C1) censored at ``clip`` around ``ellipse`` (full-image px; ``roi`` from ``(u0, v0)``).

    Parameters
    ----------
    roi : (H, W) grey on the detector's (linearised) scale
    u0, v0 : the window's offset in the image
    ellipse : (u, v, a, b, theta) the detector's fit, semi-axes
    sigma_px : the detector's edge width (start value)
    clip : the top code on the same scale as ``roi``
    dark : dark target on a bright plate; False: a bright target on a dark plate, whose
        clipped level is the target's (the profile is read inwards, the contour then
        lies outside the true one); None: from the levels, the darker side inside (the
        median more than 1 px inside against that from 1 px to ``4 sigma + 2`` px outside)

    Returns
    -------
    ClipFit; ``ok`` False (and ``delta_px`` 0) when the plate is not clipped, the band
    is too small or the fit failed.
    """
    none = ClipFit(0.0, float("nan"), float("nan"), float("nan"), 0.0, False)
    H, W = roi.shape
    d = _signed_distance(H, W, u0, v0, ellipse)
    if dark is None:
        inside = roi[d < -1.0]
        outside = roi[(d > 1.0) & (d < 4.0 * sigma_px + 2.0)]
        if inside.size < 5 or outside.size < 5:
            return none
        dark = float(np.median(inside)) < float(np.median(outside))
    # distance towards the bright side, where the clipped level is
    d = d if dark else -d
    sig0 = float(np.clip(sigma_px if np.isfinite(sigma_px) else 1.0, 0.3, 5.0))
    band = np.abs(d) < 4.0 * sig0 + 2.0
    g = roi[band].astype(np.float64)
    dd = d[band]
    if g.size < MIN_BAND_PIXELS:
        return none
    clipped = g >= clip - 1e-9
    share = float(clipped.mean())
    inner = dd < -2.0 * sig0 - 1.0
    if share < MIN_CLIPPED_SHARE or inner.sum() < 5:
        return ClipFit(0.0, float("nan"), float("nan"), sig0, share, False)
    D0 = float(np.median(g[inner]))
    if not clip > D0:
        return ClipFit(0.0, float("nan"), D0, sig0, share, False)

    def resid(p: np.ndarray) -> np.ndarray:
        D, P, sg, de = p
        return np.asarray(np.minimum(D + (P - D) * ndtr((dd - de) / sg), clip) - g)

    try:
        sol = least_squares(
            resid,
            [D0, clip + 0.05 * (clip - D0), sig0, 0.0],
            bounds=([-np.inf, clip, 0.2, -5.0], [clip, np.inf, 10.0, 5.0]),
        )
    except (ValueError, np.linalg.LinAlgError):
        return ClipFit(0.0, float("nan"), D0, sig0, share, False)
    D, P, sg, de = (float(v) for v in sol.x)
    # clipping can only hide a brighter level, which puts the true contour on the bright
    # side (de > 0); a plate fitted at the clip level or a contour moved the other way
    # is a profile (C1) does not describe (a lens's own edge spread, sharpening): no change
    above = P - clip > MIN_HIDDEN_CONTRAST * (clip - D)
    ok = bool(sol.success and np.isfinite(de) and 0.0 < de < 4.9 and above)
    outward = de if dark else -de
    return ClipFit(outward if ok else 0.0, P, D, sg, share, ok)
