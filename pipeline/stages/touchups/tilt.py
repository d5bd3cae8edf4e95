"""Touch-up extraction: the tilt bias of a tilted target's ellipse.

A tilted circle images as an ellipse whose centre is not the image of the
circle's centre and whose long axis exceeds the untilted size;
:func:`tilt_bias` gives both offsets per touch-up, with the camera taken from the
image Jacobian (:mod:`pipeline.stages.touchups.jacobian`). The steps are described
in :mod:`pipeline.stages.touchups.stage`.
"""

from __future__ import annotations

import numpy as np

from pipeline.measurement.image import camera_from_jacobian


def tilt_bias(
    shape: np.ndarray,
    T_base_flange: np.ndarray,
    labels: np.ndarray,
    J: np.ndarray,
    s0: float,
    geometric: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets between the ellipse and the projected circle centre / untilted size.

    A circle of radius ``R`` at distance ``z`` whose plane is tilted by ``theta``
    images as an ellipse with ``b / a = cos(theta)`` (``a = f R / z``), whose centre
    lies off the image of the circle's centre by ``(a^2 / f) sin(theta) cos(theta)``
    along the minor axis, away from the side the plate normal leans to, and
    whose long axis exceeds ``f 2R / z`` by ``s (a / f)^2 sin^2(theta) / 2`` (second
    order expansion of the perspective projection of the tilted circle).
    ``f`` comes from the image Jacobian (:func:`camera_from_jacobian`). Which end
    of the minor axis the normal leans to is ambiguous in one image; the sign
    is chosen per target so that the plate normals of all its touch-ups agree
    in the base frame (nominal flange orientations, camera orientation from ``J``).

    The axis ratio reads a print's own out-of-roundness as tilt: a face-on view of a
    print 0.3 % out of round reads 4.4 deg, a centre offset of a twentieth of a pixel in
    a direction that turns with the print (0.15 mm of shape error on a UR5e-like cell
    at 240 mm with 60 um out-of-round prints viewed within 8 deg of face-on). So the
    ratio only votes for the target's plate normal ``N`` (the sum of its touch-ups'
    sign-resolved normals), and each view's tilt is then that of ``N`` in its camera
    frame, ``n_c = (R_base_flange R_flange_camera)^T N``::

        cos theta_i = -n_c,z,    sin theta_i = |n_c,xy|,    minor axis along n_c,xy       (T2)

    (the nominal flange orientations: their errors of a few tenths of a degree move the
    offset by thousandths of a pixel).

    Parameters
    ----------
    shape : (n, 5) per touch-up: u, v, s, s_minor, long-axis angle (NaN if lost)
    T_base_flange : (n, 4, 4) nominal flange poses at the final captures
    labels : (n,) target labels
    J : (3, 3) image Jacobian
    s0 : designated size
    geometric : each view's tilt from its target's plate normal (T2), not from its own
        ellipse's axis ratio (which an out-of-round print shares)

    Returns
    -------
    bias : (n, 3) ``(du, dv, ds)``: add du, dv to the ellipse centre, subtract ds
        from its long axis (0 where not resolved)
    tilt_deg : (n,) tilt of the plate from the image (NaN if lost)
    resolved : (n,) the sign was resolved (at least two touch-ups of the target
        with distinct orientations, or a negligible tilt)
    """
    n = len(shape)
    bias = np.zeros((n, 3))
    resolved = np.zeros(n, dtype=bool)
    ok = np.all(np.isfinite(shape), axis=1)
    a = 0.5 * shape[:, 2]
    b = 0.5 * shape[:, 3]
    cos_t = np.clip(np.where(ok, b / np.where(ok, a, 1.0), 1.0), 0.0, 1.0)
    sin_t = np.sqrt(1.0 - cos_t**2)
    tilt_deg = np.where(ok, np.degrees(np.arccos(cos_t)), np.nan)
    try:
        R_fc, f, _ = camera_from_jacobian(J, s0)
    except (np.linalg.LinAlgError, ValueError):
        return bias, tilt_deg, resolved
    if not np.isfinite(f) or f <= 0:
        return bias, tilt_deg, resolved
    phi = shape[:, 4]
    m = np.stack([-np.sin(phi), np.cos(phi)], axis=1)  # minor-axis direction (u, v)
    n_cam = np.stack([sin_t * m[:, 0], sin_t * m[:, 1], -cos_t], axis=1)
    n_base = np.einsum("nij,jk,nk->ni", T_base_flange[:, :3, :3], R_fc, np.nan_to_num(n_cam))
    n_flip = np.einsum(
        "nij,jk,nk->ni",
        T_base_flange[:, :3, :3],
        R_fc,
        np.nan_to_num(n_cam * np.array([-1.0, -1.0, 1.0])),
    )
    sign = np.ones(n)
    for g in np.unique(labels):
        idx = [int(i) for i in np.nonzero((labels == g) & ok)[0]]
        if not idx:
            continue
        if len(idx) == 1:
            resolved[idx[0]] = bool(tilt_deg[idx[0]] < 2.0)
            continue
        best = _signs(n_base[idx], n_flip[idx])
        sign[idx] = best
        resolved[idx] = True
        N = np.where(best[:, None] > 0, n_base[idx], n_flip[idx]).sum(axis=0)
        if geometric and np.linalg.norm(N) > 0:  # (T2): each view's tilt from the normal
            R_bc = np.einsum("nij,jk->nik", T_base_flange[idx, :3, :3], R_fc)
            cos_t[idx], sin_t[idx], m[idx], tilt_deg[idx] = _view_tilts(N, R_bc, m[idx])
            sign[idx] = 1.0
    shift = (a**2 / f) * sin_t * cos_t
    bias[:, 0] = np.where(ok & resolved, sign * shift * m[:, 0], 0.0)
    bias[:, 1] = np.where(ok & resolved, sign * shift * m[:, 1], 0.0)
    bias[:, 2] = np.where(ok, shape[:, 2] * (a / f) ** 2 * sin_t**2 / 2.0, 0.0)
    return bias, tilt_deg, resolved


def _signs(n_base: np.ndarray, n_flip: np.ndarray) -> np.ndarray:
    """Which end of each view's minor axis the normal leans to (+1: ``n_base``, -1:
    ``n_flip``): the choice whose normals agree best (the longest sum; every choice up to
    ten views, else coordinate ascent)."""
    k = len(n_base)
    if k <= 10:
        best, best_sc = np.ones(k), -1.0
        for code in range(1 << k):
            sg = np.array([(-1.0 if (code >> jj) & 1 else 1.0) for jj in range(k)])
            sc = float(np.linalg.norm(np.where(sg[:, None] > 0, n_base, n_flip).sum(axis=0)))
            if sc > best_sc:
                best, best_sc = sg, sc
        return best
    sg = np.ones(k)
    for _ in range(5):
        for j in range(k):
            rest = np.where(sg[:, None] > 0, n_base, n_flip).sum(axis=0)
            rest -= n_base[j] if sg[j] > 0 else n_flip[j]
            sg[j] = 1.0 if n_base[j] @ rest >= n_flip[j] @ rest else -1.0
    return sg


def _view_tilts(
    N: np.ndarray, R_base_camera: np.ndarray, m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(T2): ``cos``, ``sin`` of each view's tilt, the minor-axis direction and the tilt
    (deg) of the plate normal ``N`` (base frame, any length) seen from cameras
    ``R_base_camera`` (k, 3, 3); a view straight along it keeps its ``m``."""
    N = N / np.linalg.norm(N)
    nc = np.einsum("nji,j->ni", R_base_camera, N)  # the normal in each camera frame
    nxy = np.hypot(nc[:, 0], nc[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        mg = nc[:, :2] / nxy[:, None]
    m_out = np.where(nxy[:, None] > 1e-12, mg, m)
    return np.clip(-nc[:, 2], 0.0, 1.0), nxy, m_out, np.degrees(np.arctan2(nxy, -nc[:, 2]))
