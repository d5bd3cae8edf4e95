"""Small pure SE(3) / SO(3) helpers, batched over leading axes.

Conventions (see ``docs/conventions.md``): ``T_a_b`` is a ``(..., 4, 4)``
homogeneous transform mapping coordinates in frame ``b`` to frame ``a``, so
``T_a_c = T_a_b @ T_b_c`` and ``p_a = T_a_b @ p_b``. Rotations ``R_a_b`` are the
upper-left ``3 x 3`` block. Angles are radians, lengths metres.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]


def skew(v: ArrayLike) -> F64:
    """Cross-product matrix ``[v]_x`` with ``[v]_x @ w == v x w``.

    Parameters
    ----------
    v : (..., 3)

    Returns
    -------
    (..., 3, 3)
    """
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def matrix_from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> F64:
    """Rotation about a unit ``axis`` by ``angle`` (Rodrigues' formula).

    ``R = I + sin(t) K + (1 - cos(t)) K^2`` with ``K = [axis]_x``.

    Parameters
    ----------
    axis : (..., 3) unit vector(s); broadcast against ``angle``.
    angle : (...) radians.

    Returns
    -------
    (..., 3, 3)
    """
    axis = np.asarray(axis, dtype=float)
    angle = np.asarray(angle, dtype=float)
    K = skew(axis)
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def matrix_from_rpy(rpy: ArrayLike) -> F64:
    """URDF fixed-axis roll-pitch-yaw: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Parameters
    ----------
    rpy : (..., 3) ``(roll, pitch, yaw)`` in radians.

    Returns
    -------
    (..., 3, 3)
    """
    rpy = np.asarray(rpy, dtype=float)
    r, p, y = rpy[..., 0], rpy[..., 1], rpy[..., 2]
    cr, sr = np.cos(r), np.sin(r)
    cp, sp = np.cos(p), np.sin(p)
    cy, sy = np.cos(y), np.sin(y)
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def rpy_from_matrix(R: ArrayLike) -> F64:
    """Inverse of :func:`matrix_from_rpy` (pitch in ``[-pi/2, pi/2]``).

    Parameters
    ----------
    R : (..., 3, 3)

    Returns
    -------
    (..., 3) ``(roll, pitch, yaw)``. At gimbal lock (``|pitch| = pi/2``) roll
    is set to 0 and the whole rotation about the vertical goes into yaw.
    """
    R = np.asarray(R, dtype=float)
    sp = np.clip(-R[..., 2, 0], -1.0, 1.0)
    cp = np.hypot(R[..., 0, 0], R[..., 1, 0])
    pitch = np.arctan2(sp, cp)
    lock = cp < 1e-12
    roll = np.where(lock, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(
        lock,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    return np.stack([roll, pitch, yaw], axis=-1)


def transform_from(R: ArrayLike, p: ArrayLike) -> F64:
    """Assemble ``T = [[R, p], [0, 1]]``.

    Parameters
    ----------
    R : (..., 3, 3)
    p : (..., 3)

    Returns
    -------
    (..., 4, 4)
    """
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def transform_from_xyz_rpy(xyz: ArrayLike, rpy: ArrayLike) -> F64:
    """URDF ``<origin xyz rpy>`` as a transform ``T_parent_joint``.

    Parameters
    ----------
    xyz, rpy : (..., 3)

    Returns
    -------
    (..., 4, 4)
    """
    return transform_from(matrix_from_rpy(rpy), xyz)


def invert_transform(T: ArrayLike) -> F64:
    """``T_b_a`` from ``T_a_b`` using ``R^T`` (exact for rigid transforms).

    Parameters
    ----------
    T : (..., 4, 4)

    Returns
    -------
    (..., 4, 4)
    """
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return transform_from(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def transform_points(T: ArrayLike, p: ArrayLike) -> F64:
    """Map points: ``p_a = R_a_b p_b + t_a_b``.

    Parameters
    ----------
    T : (..., 4, 4) ``T_a_b``
    p : (..., 3) points in frame ``b`` (broadcast against ``T``)

    Returns
    -------
    (..., 3) points in frame ``a``.
    """
    T = np.asarray(T, dtype=float)
    p = np.asarray(p, dtype=float)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def translation(p: ArrayLike) -> F64:
    """Pure translation transform, ``(..., 3) -> (..., 4, 4)``."""
    p = np.asarray(p, dtype=float)
    return transform_from(np.broadcast_to(np.eye(3), p.shape[:-1] + (3, 3)), p)


def rotation_angle(R: ArrayLike) -> F64:
    """Angle of a rotation matrix, robust near 0 and pi.

    Parameters
    ----------
    R : (..., 3, 3)

    Returns
    -------
    (...) angle in ``[0, pi]``.
    """
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    w = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    return np.arctan2(0.5 * np.linalg.norm(w, axis=-1), 0.5 * (tr - 1.0))
