"""Sub-pixel detection of the circular target's image ellipse.

The measuring data of one image (../shared/spec/recording.md) are the centre
``(u, v)`` and the full long axis ``s`` of the ellipse fitting the target
contour, the contour being the boundary at the grey level halfway between
target and plate. :func:`detect_target` estimates them in four steps:

1. **Coarse blob** on a 4x area-downsampled copy: plate level = median, the
   target's extreme level = min (dark on light) or max; threshold halfway;
   connected components; the blob is picked by size and, when an expected
   ``(u, v, s)`` is given, by distance to it. Competing blobs are counted and
   an ambiguity ratio reported.
2. **Local levels** in a full-resolution window around the blob: surfaces
   ``g_in(u, v)``, ``g_out(u, v)`` (planes plus one shared vignetting
   curvature, :func:`_level_surfaces`) fitted to the pixels well inside and
   well outside the blob (absorbs shading and vignetting), giving the halfway level
   ``g_mid = (g_in + g_out) / 2`` at every pixel.
3. **Sub-pixel edge points**: the zero crossings of ``g - g_mid`` along every
   row and column of the window, by linear interpolation between the two
   pixel centres that straddle it. A crossing on a row is used where the
   contour normal is within 60 deg of the row (``|n_u| >= 0.5``), a crossing
   on a column where ``|n_v| >= 0.5`` (normal from a first fit). Linear
   interpolation errs in opposite directions for opposite sub-pixel phases,
   and a contour sweeps all phases, so the fit is not biased by the grid.
4. **Ellipse fit** (algebraic conic fit on normalised coordinates, then
   Gauss-Newton on the geometric distances) and a **curvature correction**:
   blurring a convex contour with an isotropic kernel of variance ``sigma^2``
   moves its halfway-level line inwards by ``sigma^2 kappa / 2`` (``kappa``
   the local curvature; for a disc of radius R: ``R - sigma^2 / (2R)``, from
   the second-order expansion of the blurred indicator). ``sigma^2`` is
   measured from the image itself: across an edge of width ``sigma``,
   ``integral p (1 - p) dn = sigma / sqrt(pi)`` for the normalised profile ``p``
   (an erf), so ``sigma = sqrt(pi) * sum p (1 - p) / perimeter``. Each edge
   point is moved out by ``sigma^2 kappa / 2`` and the ellipse refitted.

Quality figures: RMS geometric fit residual (px), completeness (share of the
ellipse's parameter angle covered by edge points), border contact, number of
competing blobs, ambiguity ratio, contrast, and the measured edge width.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from scipy.special import ndtr

from pipeline.stages.ellipse_distance import approx_distance
from pipeline.stages.response import Response, parse_response

try:  # the compiled fine stage (same steps, loops compiled by numba)
    from pipeline.stages import _detect_jit as _jit
except ImportError:  # pragma: no cover - numba missing: NumPy path
    _jit = None  # type: ignore[assignment]

POLARITIES = ("dark_on_light", "light_on_dark")
_KER3 = np.ones((3, 3), np.uint8)  # 3x3 structuring element of the core / plate masks


@dataclass
class DetectConfig:
    """Detection settings.

    Attributes
    ----------
    polarity : {"dark_on_light", "light_on_dark"} or None
        None: from the recording's metadata (ingest fills it) or automatic.
    downsample : int
        Factor of the coarse blob search.
    min_area_px : float
        Smallest blob (full-resolution px^2) considered a target.
    max_area_frac : float
        Largest blob as a share of the image.
    min_contrast_frac : float
        Least ``|g_out - g_in| / max(g_out, g_in)``; lower is "no target".
    max_edge_sigma_px : float
        Edges wider than this (motion blur, out-of-focus occluder) mark the
        detection as blurred (``found`` stays True, ``quality_ok`` False).
    min_completeness : float
        Below this share of contour the detection is flagged incomplete.
    curvature_correction : bool
        Apply the blur-curvature correction of step 4.
    ambiguity_ratio : float
        A competing blob at least this fraction of the chosen one's area (and
        not clearly excluded by the expected position) flags ``ambiguous``.
    compiled : bool
        Run the fine stage compiled (:mod:`pipeline.stages._detect_jit`, numba)
        when numba is installed; False: the NumPy reference path.
    response : str
        The camera's response curve (:mod:`pipeline.stages.response`: ``linear``,
        ``srgb``, ``gamma:G``): the grey levels of the target's window are
        linearised with its inverse before the sub-pixel stage, so that the
        halfway level is halfway in irradiance. ``auto`` (the default): ingest
        takes the recording's ``camera_response`` metadata or estimates the
        curve from the first images (:func:`pipeline.stages.response_estimate.estimate_response`);
        :func:`detect_target` called alone treats ``auto`` as ``linear``.
    clip_correction : bool
        Where the bright side of the edge is clipped at the image type's top code
        (an over-exposed plate), move the contour to where the unclipped halfway
        level would be, by a censored fit of the edge profile
        (:mod:`pipeline.stages.saturation`); the long and short axes grow by the
        ``clip_correction_px`` of the result.
    """

    polarity: str | None = None
    downsample: int = 4
    min_area_px: float = 30.0
    max_area_frac: float = 0.25
    min_contrast_frac: float = 0.25
    max_edge_sigma_px: float = 2.0
    min_completeness: float = 0.9
    curvature_correction: bool = True
    ambiguity_ratio: float = 0.5
    compiled: bool = True
    response: str = "auto"
    clip_correction: bool = True

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: keys of the dict :func:`detect_target` returns (also the detections columns)
RESULT_KEYS = (
    "found",
    "u",
    "v",
    "s",
    "s_minor",
    "angle",
    "s_inv",
    "residual_px",
    "completeness",
    "border_contact",
    "n_blobs",
    "ambiguity",
    "ambiguous",
    "contrast",
    "edge_sigma_px",
    "clip_correction_px",
    "n_edge_points",
    "quality_ok",
    "reason",
)


def empty_result(reason: str, n_blobs: int = 0) -> dict[str, Any]:
    nan = float("nan")
    return {
        "found": False,
        "u": nan,
        "v": nan,
        "s": nan,
        "s_minor": nan,
        "angle": nan,
        "s_inv": nan,
        "residual_px": nan,
        "completeness": 0.0,
        "border_contact": False,
        "n_blobs": n_blobs,
        "ambiguity": 0.0,
        "ambiguous": False,
        "contrast": nan,
        "edge_sigma_px": nan,
        "clip_correction_px": nan,
        "n_edge_points": 0,
        "quality_ok": False,
        "reason": reason,
    }


# ----------------------------------------------------------------- ellipse math


def fit_conic(pts: np.ndarray) -> np.ndarray | None:
    """Algebraic conic fit ``A x^2 + B xy + C y^2 + D x + E y + F = 0``.

    Minimises ``sum (conic(x_i))^2`` with ``|coefficients| = 1``: the smallest
    right singular vector of the design matrix (here the eigenvector of its
    scatter matrix), on centred, scaled points (Hartley-style normalisation),
    mapped back to pixel coordinates.

    Parameters
    ----------
    pts : (N, 2), N >= 5

    Returns
    -------
    (6,) conic coefficients in pixel coordinates, or None if degenerate.
    """
    if pts.shape[0] < 6:
        return None
    m = pts.mean(axis=0)
    q = pts - m
    sc = float(np.sqrt(np.mean(np.sum(q * q, axis=1))))
    if not sc > 0:
        return None
    x = q[:, 0] / sc
    y = q[:, 1] / sc
    D = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    # smallest eigenvector of the scatter matrix = smallest right singular vector
    _, V = np.linalg.eigh(D.T @ D)
    a, b, c, d, e, f = V[:, 0]
    # undo scaling then translation: x = (X - mx)/sc
    a, b, c, d, e = a / sc**2, b / sc**2, c / sc**2, d / sc, e / sc
    mx, my = m
    A, B, C = a, b, c
    Dn = d - 2 * a * mx - b * my
    En = e - 2 * c * my - b * mx
    Fn = f + a * mx * mx + b * mx * my + c * my * my - d * mx - e * my
    return np.array([A, B, C, Dn, En, Fn])


def conic_to_params(k: np.ndarray) -> tuple[float, float, float, float, float] | None:
    """Conic -> ``(u, v, a, b, theta)``: centre, semi-axes ``a >= b``, long-axis angle.

    ``theta`` is measured from ``+u`` towards ``+v``, in ``(-pi/2, pi/2]``.
    Returns None when the conic is not a real ellipse.
    """
    A, B, C, D, E, F = k
    det = 4 * A * C - B * B
    if det <= 0:
        return None
    # centre: gradient zero, [[2A, B], [B, 2C]] (x0, y0) = (-D, -E)
    x0 = (B * E - 2 * C * D) / det
    y0 = (B * D - 2 * A * E) / det
    F0 = F + 0.5 * (D * x0 + E * y0)
    # eigen-decomposition of [[A, B/2], [B/2, C]] in closed form
    half_diff = 0.5 * (A - C)
    rad = float(np.hypot(half_diff, 0.5 * B))
    mean_ac = 0.5 * (A + C)
    lam = np.array([mean_ac - rad, mean_ac + rad])
    phi = 0.5 * float(np.arctan2(B, A - C))  # direction of the larger eigenvalue
    vec = np.array([[-np.sin(phi), np.cos(phi)], [np.cos(phi), np.sin(phi)]])
    if F0 > 0:
        lam, F0 = -lam, -F0
    if np.any(lam <= 0) or F0 >= 0:
        return None
    ax = np.sqrt(-F0 / lam)
    i = int(np.argmax(ax))
    d = vec[:, i]
    th = float(np.arctan2(d[1], d[0]))
    if th <= -np.pi / 2:
        th += np.pi
    elif th > np.pi / 2:
        th -= np.pi
    return float(x0), float(y0), float(ax[i]), float(ax[1 - i]), th


def ellipse_foot(
    pts: np.ndarray, p: tuple[float, float, float, float, float], newton: int = 4
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed geometric distance of points to an ellipse, the foot angle and curvature.

    Uses a few Newton steps on the parameter angle ``t`` of the closest point
    ``(a cos t, b sin t)`` in the ellipse frame.

    Returns
    -------
    dist : (N,) signed distance, positive outside
    t : (N,) parameter angle of the foot point
    kappa : (N,) curvature of the ellipse at the foot point, 1/px
    """
    u0, v0, a, b, th = p
    c, s = np.cos(th), np.sin(th)
    du = pts[:, 0] - u0
    dv = pts[:, 1] - v0
    x = c * du + s * dv
    y = -s * du + c * dv
    t = np.arctan2(a * y, b * x)
    for _ in range(newton):
        ct, st = np.cos(t), np.sin(t)
        # f(t) = (a^2 - b^2) ct st - x a st + y b ct = 0
        f = (a * a - b * b) * ct * st - x * a * st + y * b * ct
        fp = (a * a - b * b) * (ct * ct - st * st) - x * a * ct - y * b * st
        t = t - f / np.where(np.abs(fp) > 1e-12, fp, 1e-12)
    ct, st = np.cos(t), np.sin(t)
    ex, ey = a * ct, b * st
    d = np.hypot(x - ex, y - ey)
    inside = (x / a) ** 2 + (y / b) ** 2 < 1.0
    d = np.where(inside, -d, d)
    kappa = a * b / np.power(a * a * st * st + b * b * ct * ct, 1.5)
    return d, t, kappa


def ellipse_normals(p: tuple[float, float, float, float, float], t: np.ndarray) -> np.ndarray:
    """Outward unit normals ``(N, 2)`` in image coordinates at parameter angles ``t``."""
    _, _, a, b, th = p
    nx = b * np.cos(t)
    ny = a * np.sin(t)
    nn = np.hypot(nx, ny)
    nx, ny = nx / nn, ny / nn
    c, s = np.cos(th), np.sin(th)
    return np.stack([c * nx - s * ny, s * nx + c * ny], axis=1)


def refine_geometric(
    pts: np.ndarray, p: tuple[float, float, float, float, float], iterations: int = 3
) -> tuple[tuple[float, float, float, float, float], np.ndarray]:
    """Gauss-Newton on the orthogonal distances of ``pts`` to the ellipse ``p``.

    Parameters ``(u, v, a, b, theta)``; the distance derivatives are those of
    the foot point (the foot moves along the contour, so only the normal
    component counts): with ``d = n . (p - c - R e(t))``, ``dd/dc = -n``,
    ``dd/da = -n . R (cos t, 0)``, ``dd/db = -n . R (0, sin t)``,
    ``dd/dtheta = -n . R' (a cos t, b sin t)``.

    Returns the refined parameters and the final residuals ``(N,)``.
    """
    q = np.array(p, dtype=float)
    d = np.zeros(len(pts))
    for _ in range(iterations):
        pp = (q[0], q[1], q[2], q[3], q[4])
        d, t, _ = ellipse_foot(pts, pp)
        n = ellipse_normals(pp, t)
        c, s = np.cos(q[4]), np.sin(q[4])
        ct, st = np.cos(t), np.sin(t)
        Ja = n[:, 0] * c * ct + n[:, 1] * s * ct
        Jb = -n[:, 0] * s * st + n[:, 1] * c * st
        ex, ey = q[2] * ct, q[3] * st
        # d(R e)/dtheta = (-s ex - c ey, c ex - s ey)
        Jt = n[:, 0] * (-s * ex - c * ey) + n[:, 1] * (c * ex - s * ey)
        J = -np.stack([n[:, 0], n[:, 1], Ja, Jb, Jt], axis=1)
        step, *_ = np.linalg.lstsq(J, -d, rcond=None)
        q = q + step
        if np.max(np.abs(step[:4])) < 1e-7:
            break
    if q[3] > q[2]:
        q[2], q[3] = q[3], q[2]
        q[4] += np.pi / 2
    q[4] = (q[4] + np.pi / 2) % np.pi - np.pi / 2
    pp = (q[0], q[1], q[2], q[3], q[4])
    d, _, _ = ellipse_foot(pts, pp)
    return pp, d


# ----------------------------------------------------------------- detection


def _level_surfaces(
    roi: np.ndarray, core: np.ndarray, outer: np.ndarray, ua: np.ndarray, va: np.ndarray
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Grey levels of the target and of the plate over the window, with vignetting.

    Model (``du, dv`` from the window centre, ``r^2 = du^2 + dv^2``)::

        g_in  = a0 + a1 du + a2 dv + k A r^2     (core pixels)
        g_out = b0 + b1 du + b2 dv + k B r^2     (outer pixels)

    The planes absorb shading. Vignetting multiplies the irradiance by a
    fall-off that is ``1 - c r'^2`` about the principal point to second order
    (cos^4 law), i.e. locally ``(1 + k r^2)`` times a plane about any centre,
    the same factor for target and plate: hence one ``k``, weighted by each
    region's level (``A``, ``B``: the levels of plain plane fits, which makes
    the model linear). Planes alone, fitted to the plate ring around the target
    and to its core, miss the level at the contour in between by the curvature
    of the fall-off: the halfway level came out 0.04 grey low for 15 % corner
    vignetting, -0.001 px of size. One shared ``k`` (7 unknowns) instead of a
    quadratic term per surface keeps the variance down on small targets, whose
    core is too small to fix a curvature of its own. Fewer than 30 pixels in
    either region: planes only (fewer than 6: the mean).

    Returns
    -------
    g_in (H, W), level_in at the window centre, g_out (H, W), level_out.
    """
    uc, vc = float(ua.mean()), float(va.mean())
    du = (ua - uc).astype(np.float64).reshape(1, -1)
    dv = (va - vc).astype(np.float64).reshape(-1, 1)
    r2 = du * du + dv * dv
    roi64 = roi.astype(np.float64)

    def cols(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return (
            np.broadcast_to(du, roi.shape)[m],
            np.broadcast_to(dv, roi.shape)[m],
            np.broadcast_to(r2, roi.shape)[m],
            roi64[m],
        )

    def plane(m: np.ndarray) -> np.ndarray:
        x, y, _, g = cols(m)
        if g.size < 6:
            return np.array([float(g.mean()) if g.size else 0.0, 0.0, 0.0])
        X = np.stack([np.ones(g.size), x, y], axis=1)
        try:
            return np.asarray(np.linalg.solve(X.T @ X + np.eye(3) * 1e-9, X.T @ g))
        except np.linalg.LinAlgError:
            return np.array([float(g.mean()), 0.0, 0.0])

    a = plane(core)
    b = plane(outer)
    lv_a, lv_b = float(a[0]), float(b[0])
    k = 0.0
    xi, yi, ri, gi = cols(core)
    xo, yo, ro, go = cols(outer)
    if gi.size >= 30 and go.size >= 30:
        n_i = gi.size
        X = np.zeros((n_i + go.size, 7))
        X[:n_i, 0], X[:n_i, 1], X[:n_i, 2], X[:n_i, 6] = 1.0, xi, yi, lv_a * ri
        X[n_i:, 3], X[n_i:, 4], X[n_i:, 5], X[n_i:, 6] = 1.0, xo, yo, lv_b * ro
        y = np.concatenate([gi, go])
        try:
            c = np.linalg.solve(X.T @ X + np.eye(7) * 1e-9, X.T @ y)
            a, b, k = c[:3], c[3:6], float(c[6])
        except np.linalg.LinAlgError:
            k = 0.0
    g_in = a[0] + a[1] * du + a[2] * dv + k * lv_a * r2
    g_out = b[0] + b[1] * du + b[2] * dv + k * lv_b * r2
    return g_in, float(a[0]), g_out, float(b[0])


def _crossings(
    roi: np.ndarray, mid: np.ndarray, amp: np.ndarray, min_step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Halfway-level crossings along rows and columns of the window.

    Returns ``(row_pts, col_pts)``, each ``(N, 2)`` in window ``(x, y)`` pixels.
    """
    h = roi - mid
    # along rows: between (y, x) and (y, x+1)
    a0, a1 = h[:, :-1], h[:, 1:]
    m = (a0 * a1 < 0) | ((a0 == 0) & (a1 != 0))
    m &= np.abs(a1 - a0) > min_step * 0.5 * (amp[:, :-1] + amp[:, 1:])
    ys, xs = np.nonzero(m)
    t = a0[ys, xs] / (a0[ys, xs] - a1[ys, xs])
    rows = np.stack([xs + t, ys.astype(float)], axis=1)
    b0, b1 = h[:-1, :], h[1:, :]
    m2 = (b0 * b1 < 0) | ((b0 == 0) & (b1 != 0))
    m2 &= np.abs(b1 - b0) > min_step * 0.5 * (amp[:-1, :] + amp[1:, :])
    ys2, xs2 = np.nonzero(m2)
    t2 = b0[ys2, xs2] / (b0[ys2, xs2] - b1[ys2, xs2])
    cols = np.stack([xs2.astype(float), ys2 + t2], axis=1)
    return rows, cols


def _unbias_crossings(
    pts: np.ndarray,
    is_row: np.ndarray,
    nrm: np.ndarray,
    sigma: float,
    kappa: np.ndarray | None = None,
) -> np.ndarray:
    """Remove the linear-interpolation error of halfway crossings.

    Along a row, an edge of width ``sigma`` (Gaussian profile, pixel area
    included) whose normal makes the angle ``alpha`` with the row has the
    profile ``Phi((x - c) / sigma')``, ``sigma' = sigma / |cos alpha|``. Linear
    interpolation between the pixel centres 0 and 1 around the crossing ``c``
    returns ``t(c) = (1/2 - Phi(-c/sigma')) / (Phi((1-c)/sigma') - Phi(-c/sigma'))``,
    which is exact only at ``c = 0, 1/2, 1``; its error is periodic in the
    sub-pixel phase and, summed over a contour, leaves a few hundredths of a pixel
    of size error that depends on where the contour falls on the grid. ``c`` is
    recovered from the measured ``t`` by fixed-point iteration ``c <- c + t - t(c)``
    (``t(c)`` is close to the identity). Columns likewise with ``|sin alpha|``.

    The contour is curved (curvature ``kappa``, outward normal ``n``): a point
    ``delta`` along the row from the crossing lies at the signed distance
    ``delta n_u + kappa delta^2 (1 - n_u^2) / 2`` from it (second-order
    expansion of the distance to a circle of radius ``1/kappa``), so both pixel
    centres sit a little farther out than on a straight edge. The model profile
    is ``Phi(d / sigma)`` of that distance. Ignoring the quadratic term moves
    the crossings inwards by ``kappa sin^2(alpha) c (1 - c) / 2`` on average over
    the phase ``c`` (about 0.001 px per side for a 54 px disc, more at the ends of
    a tilted target's long axis), a size error that does not depend on the blur.
    """
    out = pts.copy()
    for col, mask in ((0, is_row), (1, ~is_row)):
        if not mask.any():
            continue
        x = pts[mask, col]
        base = np.floor(x)
        t = x - base
        nc = nrm[mask, col]
        na = np.maximum(np.abs(nc), 0.3)
        if kappa is None:
            q = np.zeros_like(na)
        else:
            q = np.sign(nc) * kappa[mask] * np.clip(1.0 - nc * nc, 0.0, 1.0) / 2.0
        c = t.copy()
        for _ in range(4):
            lo = ndtr((-c * na + q * c * c) / sigma)
            hi = ndtr(((1.0 - c) * na + q * (1.0 - c) ** 2) / sigma)
            tc = (0.5 - lo) / np.maximum(hi - lo, 1e-12)
            c = np.clip(c + (t - tc), 0.0, 1.0)
        out[mask, col] = base + c
    return out


def _completeness(t: np.ndarray, bins: int = 36) -> float:
    """Share of ``bins`` equal sectors of the parameter angle holding an edge point."""
    idx = ((np.mod(t, 2 * np.pi) / (2 * np.pi)) * bins).astype(int) % bins
    return float(np.mean(np.bincount(idx, minlength=bins) > 0))


def _edge_width(
    roi: np.ndarray,
    uu: np.ndarray,
    vv: np.ndarray,
    g_in: np.ndarray,
    g_out: np.ndarray,
    outer: np.ndarray,
    p: tuple[float, float, float, float, float],
    completeness: float,
) -> tuple[float, float]:
    """Edge width ``sigma`` (px) and grey noise, from the normalised edge profile.

    ``sigma = sqrt(pi) * sum_band p (1 - p) / L`` with ``p = (g - g_in) / (g_out - g_in)``
    clipped to ``[0, 1]``, the sum over pixels within 3 px of the contour, ``L``
    the visible contour length. Grey noise ``eps`` (in units of the contrast)
    biases every term: with ``p = mu + eps Z`` clipped, ``E[p (1 - p)] - mu (1 - mu)``
    is ``+eps / sqrt(2 pi)`` on the flat pixels (clipping keeps only the positive
    half) and ``-eps^2`` on the steep part. The expected bias of each band pixel
    is removed, with ``mu = Phi(d / sigma)`` from its distance ``d`` to the contour
    (:func:`noise_bias_pq`), ``sigma`` from the previous pass (two passes). A
    cruder count (every pixel but ``2 L`` treated as flat) left ``sigma`` 3 %
    short at 2 grey levels of noise, 0.003 px short in ``s`` after the
    curvature correction.
    """
    u0, v0, a, b, th = p
    c, s = np.cos(th), np.sin(th)
    du = uu - u0
    dv = vv - v0
    x = (c * du + s * dv) / a
    y = (-s * du + c * dv) / b
    rho = np.sqrt(x * x + y * y) + 1e-12
    # first-order distance to the contour: (rho - 1) / |grad rho|
    gx = x / (a * rho)
    gy = y / (b * rho)
    dist = (rho - 1.0) / np.sqrt(gx * gx + gy * gy)
    band = np.abs(dist) < 3.0
    diff = g_out - g_in
    diff = np.where(np.abs(diff) > 1e-9, diff, 1e-9)
    pq = np.clip((roi[band] - g_in[band]) / diff[band], 0.0, 1.0)
    noise = float(np.std(roi[outer] - g_out[outer])) if outer.sum() > 10 else 0.0
    contrast = float(np.mean(np.abs(diff[band]))) if band.any() else 1.0
    eps = noise / max(contrast, 1e-9)
    h = ((a - b) / (a + b)) ** 2
    perim = np.pi * (a + b) * (1 + 3 * h / (10 + np.sqrt(4 - 3 * h))) * max(completeness, 1e-3)
    raw_sum = float(np.sum(pq * (1 - pq)))
    db = dist[band]
    sigma = float(np.sqrt(np.pi) * max(raw_sum, 0.0) / perim)
    for _ in range(2):
        mu = ndtr(db / max(sigma, 0.05))
        edge_sum = raw_sum - float(np.sum(noise_bias_pq(mu, eps)))
        sigma = float(np.sqrt(np.pi) * max(edge_sum, 0.0) / perim)
    return sigma, noise


def noise_bias_pq(mu: np.ndarray, eps: float) -> np.ndarray:
    """Bias ``E[c (1 - c)] - mu (1 - mu)`` of ``c = clip(mu + eps Z, 0, 1)``, ``Z ~ N(0, 1)``.

    With ``a = -mu / eps``, ``b = (1 - mu) / eps``, ``P = Phi(b) - Phi(a)`` (truncated
    normal moments; ``c (1 - c) = 0`` outside ``[0, 1]``):

        E[X; 0<X<1]   = mu P + eps (phi(a) - phi(b))
        E[X^2; 0<X<1] = mu^2 P + 2 mu eps (phi(a) - phi(b)) + eps^2 (P + a phi(a) - b phi(b))

    Parameters
    ----------
    mu : (N,) noise-free normalised grey levels in ``[0, 1]``
    eps : grey noise in units of the contrast

    Returns
    -------
    (N,) expected bias of each pixel's ``p (1 - p)`` term.
    """
    mu = np.asarray(mu, dtype=float)
    if eps <= 0:
        return np.zeros_like(mu)
    a = -mu / eps
    b = (1.0 - mu) / eps
    pa = np.exp(-0.5 * a * a) / np.sqrt(2 * np.pi)
    pb = np.exp(-0.5 * b * b) / np.sqrt(2 * np.pi)
    P = ndtr(b) - ndtr(a)
    m1 = mu * P + eps * (pa - pb)
    m2 = mu * mu * P + 2 * mu * eps * (pa - pb) + eps * eps * (P + a * pa - b * pb)
    return m1 - m2 - mu * (1.0 - mu)


@lru_cache(maxsize=16)
def _response(spec: str) -> Response | None:
    """The response of a spec string; None when linear (nothing to do)."""
    r = parse_response(spec)
    return None if r is None or r.is_linear else r


def _auto_polarity(bg: float, lo: float, hi: float) -> str:
    return "dark_on_light" if (bg - lo) >= (hi - bg) else "light_on_dark"


def detect_target(
    image: np.ndarray,
    config: DetectConfig | None = None,
    expected: tuple[float, float, float] | None = None,
) -> dict[str, Any]:
    """Find the target ellipse in one grey image.

    The ellipse of :func:`_detect` and, where the bright side of the edge is clipped,
    its censored-profile correction (:func:`_unclip`).

    Parameters
    ----------
    image : (H, W) uint8 / uint16 / float
        Grey image, ``u`` = column, ``v`` = row, pixel centres at integers.
    config : DetectConfig
    expected : (u, v, s), optional
        Where the target is expected (e.g. the previous capture): picks the
        blob closest to it among competitors.

    Returns
    -------
    dict with the keys :data:`RESULT_KEYS`: ``found``, centre ``u, v`` (px),
    full long axis ``s`` and short axis ``s_minor`` (px), long-axis ``angle``
    (rad from +u towards +v), ``s_inv = 1/s``, and the quality figures.
    ``reason`` is "" for a clean detection, else a short tag (``no_blob``,
    ``low_contrast``, ``fit_failed``, ``incomplete``, ``border``, ``ambiguous``,
    ``blurred``).
    """
    cfg = config or DetectConfig()
    out = _detect(image, cfg, expected)
    if out["found"] and cfg.clip_correction:
        out = _unclip(np.asarray(image), out, cfg)
    return out


def _detect(
    image: np.ndarray, cfg: DetectConfig, expected: tuple[float, float, float] | None
) -> dict[str, Any]:
    """:func:`detect_target` without the clipped-edge correction."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"detect_target needs a 2-D grey image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    H, W = img.shape
    k = max(int(cfg.downsample), 1)
    Ws, Hs = W // k, H // k
    # plain subsampling: the coarse search only needs the blob, and a threshold
    # halfway between the levels is many noise sigmas from both
    if img.dtype == np.uint8 and cfg.compiled and _jit is not None and Hs > 0 and Ws > 0:
        # one compiled pass: the same subsample, median and extremes
        small, bg, lo, hi = _jit.coarse_uint8(img, k)
    else:
        small = np.ascontiguousarray(img[k // 2 : Hs * k : k, k // 2 : Ws * k : k])
        sub = small[::2, ::2].ravel()
        bg = float(np.partition(sub, sub.size // 2)[sub.size // 2])
        lo, hi, _, _ = cv2.minMaxLoc(small)
    pol = cfg.polarity or _auto_polarity(bg, lo, hi)
    if pol not in POLARITIES:
        raise ValueError(f"unknown polarity {pol!r}")
    dark = pol == "dark_on_light"
    ext = lo if dark else hi
    if abs(bg - ext) / max(bg, ext, 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast")
        out["contrast"] = abs(bg - ext)
        return out
    thr = 0.5 * (bg + ext)
    mask = (small < thr) if dark else (small > thr)
    contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    kk = float(k * k)
    cand = []
    for c in contours:
        x0c, y0c, wc, hc = cv2.boundingRect(c)
        # blob area ~ polygon area + half the boundary (pixel-centre contour)
        area = (cv2.contourArea(c) + 0.5 * len(c) + 1.0) * kk
        if area < cfg.min_area_px or area > cfg.max_area_frac * H * W:
            continue
        m = cv2.moments(c)
        if m["m00"] > 0:
            cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
        else:
            cx, cy = x0c + 0.5 * (wc - 1), y0c + 0.5 * (hc - 1)
        cand.append((area, cx * k + k // 2, cy * k + k // 2, (x0c, y0c, wc, hc), c))
    if not cand:
        return empty_result("no_blob")
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
        order = sorted(range(len(cand)), key=lambda i: -areas[i])
    best = order[0]
    ambiguity = 0.0
    ambiguous = False
    if len(cand) > 1:
        second = order[1]
        ambiguity = float(min(areas[second], areas[best]) / max(areas[best], areas[second]))
        if use_exp:
            ambiguous = bool(score[second] < score[best] + 0.5 and ambiguity > cfg.ambiguity_ratio)
        else:
            ambiguous = ambiguity > cfg.ambiguity_ratio
    n_blobs = len(cand)
    x0s, y0s, ws, hs = cand[best][3]
    contour = cand[best][4].reshape(-1, 2).astype(np.float64) * k + k // 2
    border = bool(x0s == 0 or y0s == 0 or x0s + ws >= Ws or y0s + hs >= Hs)
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
        return empty_result("fit_failed", n_blobs)
    resp = _response(cfg.response)
    if resp is not None:
        # sub-pixel stage on irradiance: the halfway level is halfway in light, not in grey
        img_roi = resp.linearise(img_roi)
    if cfg.compiled and _jit is not None:
        return _finish_compiled(
            img_roi.astype(np.float64),
            core_b,
            outer,
            u0,
            v0,
            contour,
            k,
            cfg,
            n_blobs,
            border,
            ambiguity,
            ambiguous,
        )
    roi = img_roi.astype(np.float32)
    ua = np.arange(u0, u1, dtype=np.float32)
    va = np.arange(v0, v1, dtype=np.float32)
    g_in, lvl_in, g_out, lvl_out = _level_surfaces(roi, core_b, outer, ua, va)
    mid = 0.5 * (g_in + g_out)
    amp = np.abs(g_out - g_in)
    contrast = float(abs(lvl_out - lvl_in))
    if contrast / max(abs(lvl_out), abs(lvl_in), 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast", n_blobs)
        out["contrast"] = contrast
        return out
    rows, cols = _crossings(roi, mid, amp, 0.15)
    rows = rows + (u0, v0)
    cols = cols + (u0, v0)
    pts = np.concatenate([rows, cols])
    nr = rows.shape[0]
    # initial ellipse from the coarse contour; keep crossings near it (other edges out)
    p0 = None
    if len(contour) >= 6:
        k0 = fit_conic(contour)
        p0 = conic_to_params(k0) if k0 is not None else None
    if p0 is not None:
        near = np.abs(approx_distance(pts, p0)) < 0.75 * k + 1.0
        k0 = fit_conic(pts[near]) if near.sum() >= 8 else None
        p0 = conic_to_params(k0) if k0 is not None else None
    if p0 is None:
        k0 = fit_conic(pts) if pts.shape[0] >= 8 else None
        p0 = conic_to_params(k0) if k0 is not None else None
    if p0 is None:
        return empty_result("fit_failed", n_blobs)
    # choose crossings by the contour normal of the first fit, drop outliers
    d0, t0, kap0 = ellipse_foot(pts, p0, newton=2)
    n0 = ellipse_normals(p0, t0)
    keep = np.concatenate([np.abs(n0[:nr, 0]) >= 0.5, np.abs(n0[nr:, 1]) >= 0.5])
    scale_d = 1.25 * float(np.mean(np.abs(d0[keep]))) + 0.05 if keep.any() else 1.0
    keep &= np.abs(d0) < max(4 * scale_d, 0.5)
    is_row = (np.arange(len(pts)) < nr)[keep]
    pts, t0, kap0, n0 = pts[keep], t0[keep], kap0[keep], n0[keep]
    if pts.shape[0] < 8:
        return empty_result("fit_failed", n_blobs)
    completeness = _completeness(t0)
    sigma, noise = _edge_width(roi, ua[None, :], va[:, None], g_in, g_out, outer, p0, completeness)
    if cfg.curvature_correction and np.isfinite(sigma) and sigma > 0:
        sig_c = min(sigma, cfg.max_edge_sigma_px)
        pts = _unbias_crossings(pts, is_row, n0, sig_c, kap0)
        pts = pts + n0 * (0.5 * sig_c**2 * kap0)[:, None]
    k1 = fit_conic(pts)
    p1 = conic_to_params(k1) if k1 is not None else None
    if p1 is None:
        return empty_result("fit_failed", n_blobs)
    res, _, _ = ellipse_foot(pts, p1, newton=2)
    return _result(
        p1,
        float(np.sqrt(np.mean(res**2))),
        completeness,
        sigma,
        int(pts.shape[0]),
        contrast,
        cfg,
        n_blobs,
        border,
        ambiguity,
        ambiguous,
    )


def _unclip(img: np.ndarray, out: dict[str, Any], cfg: DetectConfig) -> dict[str, Any]:
    """Correct a detection whose edge is clipped at the image type's top code.

    The window around the ellipse (its semi-axis plus ``4 sigma + 3`` px) is linearised
    like the sub-pixel stage's and handed to
    :func:`pipeline.stages.saturation.fit_clipped_edge`, which takes the polarity from
    the levels (the darker side inside: dark on light). Nothing changes where no pixel
    of the window is at the top code.
    """
    from pipeline.stages import saturation

    if img.ndim != 2:
        return out
    top = saturation.clip_level(img.dtype)
    if top is None:
        return out
    u, v, s = float(out["u"]), float(out["v"]), float(out["s"])
    sig = float(out["edge_sigma_px"]) if math.isfinite(float(out["edge_sigma_px"])) else 1.0
    pad = 0.5 * s + 4.0 * min(max(sig, 0.3), 5.0) + 3.0
    H, W = img.shape
    u0, v0 = max(int(u - pad), 0), max(int(v - pad), 0)
    u1, v1 = min(int(u + pad) + 2, W), min(int(v + pad) + 2, H)
    raw = img[v0:v1, u0:u1]
    if raw.size == 0 or not bool((raw >= top).any()):
        return out
    roi = raw.astype(np.float64)
    clip = top
    resp = _response(cfg.response)
    if resp is not None:
        roi = np.asarray(resp.linearise(raw), dtype=np.float64)
        clip = float(np.asarray(resp.linearise(np.array([[top]], dtype=img.dtype)))[0, 0])
    ell = (u, v, 0.5 * s, 0.5 * float(out["s_minor"]), float(out["angle"]))
    fit = saturation.fit_clipped_edge(roi, float(u0), float(v0), ell, sig, clip, dark=None)
    if not fit.ok:
        return out
    out = dict(out)
    out["s"] = s + 2.0 * fit.delta_px
    out["s_minor"] = float(out["s_minor"]) + 2.0 * fit.delta_px
    out["s_inv"] = 1.0 / out["s"]
    out["clip_correction_px"] = 2.0 * fit.delta_px
    return out


def _finish_compiled(
    roi: np.ndarray,
    core: np.ndarray,
    outer: np.ndarray,
    u0: int,
    v0: int,
    contour: np.ndarray,
    k: int,
    cfg: DetectConfig,
    n_blobs: int,
    border: bool,
    ambiguity: float,
    ambiguous: bool,
) -> dict[str, Any]:
    """Steps 2-5 through :func:`pipeline.stages._detect_jit.fine_stage`."""
    assert _jit is not None
    r = _jit.fine_stage(
        roi,
        core,
        outer,
        float(u0),
        float(v0),
        np.ascontiguousarray(contour[:, 0]),
        np.ascontiguousarray(contour[:, 1]),
        0.75 * k + 1.0,
        bool(cfg.curvature_correction),
        float(cfg.max_edge_sigma_px),
        0.15,
    )
    lvl_in, lvl_out = float(r[10]), float(r[11])
    contrast = abs(lvl_out - lvl_in)
    if contrast / max(abs(lvl_out), abs(lvl_in), 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast", n_blobs)
        out["contrast"] = contrast
        return out
    if r[0] != 0:
        return empty_result("fit_failed", n_blobs)
    return _result(
        (r[1], r[2], r[3], r[4], r[5]),
        float(r[6]),
        float(r[7]),
        float(r[8]),
        int(r[9]),
        contrast,
        cfg,
        n_blobs,
        border,
        ambiguity,
        ambiguous,
    )


def _result(
    p: tuple[float, float, float, float, float],
    res_rms: float,
    completeness: float,
    sigma: float,
    n_pts: int,
    contrast: float,
    cfg: DetectConfig,
    n_blobs: int,
    border: bool,
    ambiguity: float,
    ambiguous: bool,
) -> dict[str, Any]:
    """The result dict of :func:`detect_target` with the quality verdict."""
    u, v, a, b, th = p
    s = 2.0 * a
    reason = ""
    quality = True
    if completeness < cfg.min_completeness:
        reason, quality = "incomplete", False
    if border:
        reason, quality = (reason or "border"), False
    if sigma > cfg.max_edge_sigma_px:
        reason, quality = (reason or "blurred"), False
    if ambiguous:
        reason, quality = (reason or "ambiguous"), False
    return {
        "found": True,
        "u": float(u),
        "v": float(v),
        "s": float(s),
        "s_minor": float(2.0 * b),
        "angle": float(th),
        "s_inv": float(1.0 / s),
        "residual_px": float(res_rms),
        "completeness": float(completeness),
        "border_contact": border,
        "n_blobs": n_blobs,
        "ambiguity": ambiguity,
        "ambiguous": ambiguous,
        "contrast": float(contrast),
        "edge_sigma_px": float(sigma),
        "clip_correction_px": 0.0,
        "n_edge_points": int(n_pts),
        "quality_ok": quality,
        "reason": reason,
    }
