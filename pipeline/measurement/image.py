"""The image side of a touch-up: its error, the size/depth relation, and what a Jacobian implies.

A touch-up drives the image of the target, its ellipse's centre ``(u, v)`` and
long axis ``s`` (px), to the designated ``(u0, v0, s0)`` (spec ``recording.md``).
Its error is

    e_T = (u - u0, v - v0, 1/s - 1/s0)                          (px, px, 1/px)

the size taken as its inverse because, for a pinhole camera of focal length ``f``
(px) and a disc of diameter ``D`` at depth ``z``,

    s = f D / z,        1/s = z / (f D),                         (S)

so ``1/s`` is linear in the stand-off. The image Jacobian ``J`` (3 x 3) maps a
small flange translation (m) to the change of ``(u, v, 1/s)``; near the optical
axis its first two rows are ``-(f/z)`` times the first two rows of
``R_camera_flange`` and its third row has norm ``1 / (f D)``
(:func:`camera_from_jacobian`). The residual correction of a touch-up that
stopped at ``e_T`` is ``d_F = -J^-1 e_T`` (:func:`residual_correction`).

Callers: the touch-up stage (:mod:`pipeline.stages.touchups.stage`, ``touchup_rows``,
``touchup_tilt``), the live loop (:class:`pipeline.live.loop.Goal`), the
simulator (:func:`pipeline.sim.cell.virtual_pin_camera`, the cell's designated
size), the report's nominal camera (:func:`pipeline.report.rrd_log.camera_guess`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.kinematics.se3 import F64


def image_error(u: Any, v: Any, s: Any, u0: Any, v0: Any, s0: Any) -> F64:
    """``e_T = (u - u0, v - v0, 1/s - 1/s0)`` (px, px, 1/px), shape (3,)."""
    return np.array([u - u0, v - v0, 1.0 / s - 1.0 / s0])


def touchup_error(
    u: float, v: float, s: float, u0: float, v0: float, s0: float, depth_scaled: bool
) -> F64:
    """``e_T`` of a touch-up that stopped at ``(u, v, s)``, its centre taken at ``s0``.

    A touch-up that stopped at size ``s`` sees a lateral offset ``x`` as
    ``(f / z) x = (s / D) x`` pixels (S), while the image Jacobian's centre rows
    hold at the designated size ``s0`` (:func:`pair_change`). So
    (``depth_scaled``) its centre errors are taken at ``s0``,
    ``e_u s0 / s``, ``e_v s0 / s``: the lateral offset they stand for, whatever
    the depth the controller stopped at. Shape (3,).
    """
    e_T = image_error(u, v, s, u0, v0, s0)
    if depth_scaled:
        e_T[:2] *= s0 / s
    return e_T


def residual_correction(J: F64, e_T: F64) -> F64:
    """``d_F = -J^-1 e_T`` (m, flange frame), zero where ``J`` is singular. Shape (3,)."""
    try:
        return np.asarray(-np.linalg.solve(J, e_T))
    except np.linalg.LinAlgError:
        return np.zeros(3)


def size_from_depth(f: float, D: float, z: float) -> float:
    """Long axis ``s = f D / z`` (px) of a disc of diameter ``D`` at depth ``z`` (S)."""
    return f * D / z


def depth_from_size(f: float, D: float, s: float) -> float:
    """Depth ``z = f D / s`` (m) at which a disc of diameter ``D`` shows long axis ``s`` (S)."""
    return f * D / s


def focal_from_size(s: float, z: float, D: float) -> float:
    """Focal length ``f = s z / D`` (px) that shows a disc of diameter ``D`` at depth ``z``
    with long axis ``s`` (S)."""
    return s * z / D


def pair_change(
    a: tuple[float, float, float], b: tuple[float, float, float], des: Any, depth_scaled: bool
) -> F64:
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
    dm = image_error(ub, vb, sb, ua, va, sa)
    if depth_scaled:
        grow = sb / sa - 1.0
        dm[0] = (dm[0] - (ua - des.u0) * grow) * des.s0 / sb
        dm[1] = (dm[1] - (va - des.v0) * grow) * des.s0 / sb
    return dm


def camera_from_jacobian(J: F64, s0: float) -> tuple[F64, float, float]:
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


def diameter_from_jacobian(J: F64, s0: float) -> float:
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


def view_geometry(J: F64, s0: float, angle: np.ndarray) -> tuple[F64, F64]:
    """What a print-size error does to a touch-up, from the image Jacobian (flange frame).

    A target whose image long axis reads ``(1 + eps)`` times what a perfect disc of
    the nominal diameter would show stops the camera ``z eps`` too far (``s = f D / z``),
    so the point that touched the target is ``p_pin + d + eps g`` with

        g = z r_z                                   (m per unit eps)

    ``r_z`` the camera's view axis and ``z`` the stand-off
    (:func:`camera_from_jacobian`). The long axis of touch-up ``k`` lies along

        l_k = cos(a_k) r_x + sin(a_k) r_y           (unit)

    ``a_k`` its image long-axis angle (from ``+u`` towards ``+v``): what
    :mod:`pipeline.stages.identify.print_shape` needs to tell an out-of-round print from the
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
