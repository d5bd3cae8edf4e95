"""Touch-up extraction, step 3: the image Jacobian and what it tells of the camera.

One image Jacobian ``J`` (3 x 3, flange translation -> ``(du, dv, ds_inv)``) for
every target, fitted row by row by Huber-robust least squares from the pairs of
consecutive still captures a small pure flange translation apart
(:func:`estimate_jacobian`), its size row scaled per target only where a print is
measurably another size (:func:`size_row_scales`); the camera orientation, focal
length and stand-off it implies (:func:`camera_from_jacobian`), the printed
diameter (:func:`diameter_from_jacobian`) and the view geometry of a print-size
error (:func:`view_geometry`). The steps are described in
:mod:`pipeline.stages.touchup`.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _huber_rows(X: np.ndarray, Y: np.ndarray, iters: int = 10) -> np.ndarray:
    """Row-wise robust fit of ``Y = X J^T``: ``X (N, 3)``, ``Y (N, 3)`` -> ``J (3, 3)``."""
    J = np.zeros((Y.shape[1], X.shape[1]))
    for r in range(Y.shape[1]):
        y = Y[:, r]
        w = np.ones(len(y))
        coef = np.zeros(X.shape[1])
        for _ in range(iters):
            sw = np.sqrt(w)
            coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
            res = y - X @ coef
            sc = 1.4826 * float(np.median(np.abs(res))) + 1e-15
            k = 1.5 * sc
            a = np.abs(res)
            w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
        J[r] = coef
    return J


def pair_change(
    a: tuple[float, float, float], b: tuple[float, float, float], des: Any, depth_scaled: bool
) -> np.ndarray:
    """One pair's change of ``(u, v, s_inv)``, taken at the designated pixel and size.

    The pairs come from the whole loop, its first probes included, taken where the
    nominal robot put the camera (millimetres off the stand-off and often tens of
    pixels off the designated pixel), while the residual correction ``-J^-1 e_T``
    applies at the designated ``(u_0, v_0, s_0)`` (``des``). For a pinhole camera and
    a disc of diameter ``D`` (image long axis ``s = f D / z``), a pair from
    ``(u_a, s_a)`` to ``(u_b, s_b)`` over a flange translation moving the target by
    ``dx`` across the view is exactly

        u_b - u_a = (u_a - c_u) (s_b / s_a - 1) + (s_b / D) dx

    (``c_u`` the principal point). So (``depth_scaled``) the centre-row change is

        du' = (u_b - u_a - (u_a - u_0) (s_b / s_a - 1)) s_0 / s_b
            = (s_0 / D) dx - (u_0 - c_u) s_0 (1 / s_b - 1 / s_a),

    linear in the translation (the last term is the off-axis part of ``J``'s depth
    column at ``u_0``), likewise for ``v``; the size row ``d s_inv / dz = 1 / (f D)``
    does not depend on depth. Without it the centre rows came out ~2 % small (the
    probes' mean depth; simulated standard cell) and the depth column ~4 mrad off.

    Parameters
    ----------
    a, b : ``(u, v, s)`` of the pair's first and second capture, px
    des : the designated values (``u0``, ``v0``, ``s0``)
    depth_scaled : False: the raw change ``(u_b - u_a, v_b - v_a, 1/s_b - 1/s_a)``

    Returns
    -------
    (3,) ``(du', dv', ds_inv)``
    """
    (ua, va, sa), (ub, vb, sb) = a, b
    dm = np.array([ub - ua, vb - va, 1.0 / sb - 1.0 / sa])
    if depth_scaled:
        grow = sb / sa - 1.0
        dm[0] = (dm[0] - (ua - des.u0) * grow) * des.s0 / sb
        dm[1] = (dm[1] - (va - des.v0) * grow) * des.s0 / sb
    return dm


def pair_scatters(pair_seg: np.ndarray, dF: np.ndarray, n: int) -> np.ndarray:
    """Each touch-up's pair scatter ``S_i = sum_{p in i} v_p v_p^T``, ``(n, 3, 3)`` m^2.

    ``v_p`` the pairs' translations ``dF`` (``(N, 3)``), ``pair_seg`` their touch-up;
    what identification weighs the nominal-to-calibrated map with
    (:mod:`pipeline.estimation.correction_frame`, F2).
    """
    S = np.zeros((n, 3, 3))
    np.add.at(S, pair_seg, dF[:, :, None] * dF[:, None, :])
    return S


def estimate_jacobian(dF: np.ndarray, dm: np.ndarray) -> np.ndarray | None:
    """Image Jacobian from pairs: ``dm (N, 3) ~ J dF (N, 3)``; None if ill-posed.

    Parameters
    ----------
    dF : (N, 3) flange-frame translations (m)
    dm : (N, 3) changes of ``(u, v, s_inv)`` (px, px, 1/px)

    Returns
    -------
    (3, 3) ``J`` with ``dm = J dF``, or None with fewer than 4 pairs or
    translations that do not span 3-D (singular value ratio < 0.05).
    """
    if len(dF) < 4:
        return None
    sv = np.linalg.svd(dF, compute_uv=False)
    if sv[-1] < 0.05 * sv[0]:
        return None
    return _huber_rows(dF, dm)


def size_row_scales(
    J: np.ndarray,
    dF: np.ndarray,
    dm: np.ndarray,
    groups: np.ndarray,
    *,
    sigmas: float,
    min_pairs: int,
) -> tuple[float, dict[int, tuple[float, float]]]:
    """Per-target scale of the image Jacobian's size row, with its standard error.

    A target of printed diameter ``D_k`` seen at the designated size has
    ``s_inv = z / (f D_k)``, so its size row is a common row times ``1 / D_k``;
    the centre rows do not depend on the target. Per target the least-squares
    scale of its pairs' size changes against the pooled row ``J_2``,

        c_k = sum(a_i b_i) / sum(a_i^2),  a_i = J_2 . dF_i,  b_i = dm_i,2,
        se(c_k) = sqrt(sum(r_i^2) / (n - 1) / sum(a_i^2)),

    is taken relative to the median target's, ``c_ref = median_k c_k`` (the
    pooled row mixes every print; the median is the prints that agree), and is
    kept where ``|c_k / c_ref - 1| > sigmas * se(c_k)``: a print measurably
    larger or smaller than the others. The rest take ``c_ref J_2``.

    Parameters
    ----------
    J : (3, 3) global image Jacobian
    dF : (N, 3) flange translations of the pairs (m)
    dm : (N, 3) their ``(u, v, s_inv)`` changes
    groups : (N,) target label of each pair

    Returns
    -------
    c_ref : the scale of the size row the targets share (1.0 with fewer than 2 targets)
    kept : ``{label: (c_k / c_ref, se)}`` for the targets whose own scale is kept
    """
    raw: dict[int, tuple[float, float]] = {}
    a_all = dF @ J[2]
    for g in np.unique(groups):
        m = groups == g
        if int(m.sum()) < min_pairs:
            continue
        a, b = a_all[m], dm[m, 2]
        saa = float(a @ a)
        if saa <= 0.0:
            continue
        c = float(a @ b) / saa
        r = b - c * a
        raw[int(g)] = (c, float(np.sqrt(float(r @ r) / max(len(a) - 1, 1) / saa)))
    if len(raw) < 2:
        return 1.0, {}
    c_ref = float(np.median([c for c, _ in raw.values()]))
    kept = {
        g: (c / c_ref, se / c_ref)
        for g, (c, se) in raw.items()
        if abs(c / c_ref - 1.0) > sigmas * se / c_ref
    }
    return c_ref, kept


def camera_from_jacobian(J: np.ndarray, s0: float) -> tuple[np.ndarray, float, float]:
    """Camera orientation in the flange frame, focal length and stand-off from ``J``.

    A flange translation ``d`` moves the target by ``-R_camera_flange d`` in the
    camera frame, so near the optical axis ``du = -(f/z) (R_cf d)_x``,
    ``dv = -(f/z) (R_cf d)_y``: the first two rows of ``J`` are ``-(f/z)`` times
    the first two rows of ``R_cf``. With ``s = f D / z``, ``s_inv = z / (f D)`` and
    ``d s_inv / dz = 1 / (f D)``, so ``z = s_inv / |J_2|`` (the third row's norm).

    Returns
    -------
    R_flange_camera : (3, 3)
    f_px : float, focal length in pixels (nominal-model metres)
    z_m : float, stand-off at the designated size
    """
    gx = float(np.linalg.norm(J[0]))
    gy = float(np.linalg.norm(J[1]))
    rx = -J[0] / gx
    ry = -J[1] / gy
    M = np.stack([rx, ry, np.cross(rx, ry)])
    U, _, Vt = np.linalg.svd(M)
    R_cf = U @ Vt
    z = (1.0 / s0) / float(np.linalg.norm(J[2]))
    f = 0.5 * (gx + gy) * z
    return R_cf.T, f, z


def diameter_from_jacobian(J: np.ndarray, s0: float) -> float:
    """The printed target diameter the image Jacobian implies, ``D = s_0 / g`` (m).

    With ``g = f / z`` the image motion per metre of lateral flange translation
    (the mean norm of ``J``'s first two rows, :func:`camera_from_jacobian`) and
    the long axis at the designated size ``s_0 = f D / z``, ``D = s_0 z / f =
    s_0 / g``. The focal length and stand-off cancel; what is left is in the
    nominal robot's metres. Near-axis approximation: off-axis views and lens
    distortion leave it ~1 % off (shipped and conformance samples: 0.3-1.1 %).

    Parameters
    ----------
    J : (3, 3) image Jacobian, rows ``(du, dv, ds_inv)`` per metre of flange translation
    s0 : designated long axis, px
    """
    g = 0.5 * (float(np.linalg.norm(J[0])) + float(np.linalg.norm(J[1])))
    return float(s0) / g if g > 0 else float("nan")


def view_geometry(J: np.ndarray, s0: float, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a print-size error does to a touch-up, from the image Jacobian (flange frame).

    A target whose image long axis reads ``(1 + eps)`` times what a perfect disc of
    the nominal diameter would show stops the camera ``z eps`` too far (``s = f D / z``),
    so the point that touched the target is ``p_pin + d + eps g`` with

        g = z r_z                                   (m per unit eps)

    ``r_z`` the camera's view axis and ``z`` the stand-off
    (:func:`camera_from_jacobian`). The long axis of touch-up ``k`` lies along

        l_k = cos(a_k) r_x + sin(a_k) r_y           (unit)

    ``a_k`` its image long-axis angle (from ``+u`` towards ``+v``): what
    :mod:`pipeline.stages.print_shape` needs to tell an out-of-round print from the
    roll of the view.

    Returns
    -------
    g : (3,) ; l : (n, 3) (NaN where the angle is)
    """
    R_fc, _, z = camera_from_jacobian(J, s0)
    g = z * R_fc[:, 2]
    a = np.asarray(angle, dtype=float)
    lvec = np.cos(a)[:, None] * R_fc[:, 0][None, :] + np.sin(a)[:, None] * R_fc[:, 1][None, :]
    return g, lvec
