"""Product of exponentials: every joint's screw axis moves as a rigid body.

Nominal POE form (Brockett 1984; Park & Okamura 1994):

    T_base_flange(q) = exp([xi_1] q_1) ... exp([xi_n] q_n) M,
    exp([xi_k] q) = G_k Rot(axis_k, q) G_k^{-1}

with ``G_k`` the home (``q = 0``) pose of joint frame ``k``. The error model
moves each home frame by a small rigid motion in its own coordinates,
``G_k' = G_k @ Delta_k``, ``Delta_k = Trans(t_k) @ Rot(exp([r_k]))``, so every
screw axis ``xi_k' = Ad(G_k Delta_k G_k^{-1}) xi_k`` is an arbitrary line and
the zero offsets are absorbed (a zero offset of joint ``k`` is a motion of all
later home frames). ``M' = G_n' @ tail`` keeps the flange fixed to the last
link (the virtual pin absorbs a flange offset). Six parameters per joint; the
two that slide or spin a joint along its own axis are redundant and dropped by
identification.

URDF write-back is exact: ``origin_k' = pre_k^{-1} G_{k-1}'^{-1} G_k'``.

Jacobian, by equation (1) of :mod:`pipeline.models.base`: ``Delta_k`` occurs
twice, once at the joint frame ``F_k`` before the motion (twist ``xi``) and,
as ``Delta_k^{-1}``, at the frame ``W_k = F_k Rot(axis_k, q_k)`` after it
(twist ``-xi``); for ``t_k`` the local twist is ``v = exp([r_k])^T e_i``, for
``r_k`` it is ``w = J_r(r_k) e_i``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain, fk_frames
from pipeline.kinematics.se3 import F64, invert_transform
from pipeline.models.base import (
    ErrorModel,
    as_points,
    joint_motions,
    point_motion,
    register,
    so3_exp_many,
    so3_right_jacobian_many,
)

_COMP = ("tx", "ty", "tz", "rx", "ry", "rz")


@register
class POEModel(ErrorModel):
    """Rigid motion of each joint's home frame (six per joint)."""

    name = "poe"
    description = "product of exponentials: each joint screw axis moves rigidly"

    def __init__(self, chain: Chain) -> None:
        super().__init__(chain)
        L = self.layout
        _, frames = fk_frames(chain, np.zeros(L.n))
        self.G = frames[0]  # (n, 4, 4) home joint frames (before the motion)
        self._pre_inv = invert_transform(L.pre)
        for jn in L.names:
            for c in _COMP:
                self.param_names.append(f"{jn}.{c}")
                self.param_joints.append(jn)
                self.param_units.append("m" if c[0] == "t" else "rad")

    def _home(self, x: ArrayLike) -> tuple[F64, F64, F64]:
        """Corrected home frames ``G_k'`` and each ``exp([r_k])``, ``r_k``."""
        x = np.asarray(x, dtype=float).reshape(self.layout.n, 6)
        E = so3_exp_many(x[:, 3:])
        H = np.empty_like(self.G)
        H[:] = np.eye(4)
        H[:, :3, :3] = E
        H[:, :3, 3] = x[:, :3]
        return self.G @ H, E, x[:, 3:]

    def _relative(self, Gp: F64) -> F64:
        """``G_{k-1}'^{-1} G_k'`` (the corrected segment from joint k-1 to k)."""
        rel = np.empty_like(Gp)
        rel[0] = Gp[0]
        rel[1:] = invert_transform(Gp[:-1]) @ Gp[1:]
        return rel

    def origins(self, x: ArrayLike) -> dict[str, F64]:
        Gp, _, _ = self._home(x)
        rel = self._relative(Gp)
        return {jn: self._pre_inv[k] @ rel[k] for k, jn in enumerate(self.layout.names)}

    def pin_and_jacobian(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
    ) -> tuple[F64, F64, F64 | None]:
        L = self.layout
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        pf = as_points(p_flange, N)
        Gp, E, r = self._home(x)
        rel = self._relative(Gp)
        M = joint_motions(L.axis, L.prismatic, q)
        Fs = np.empty((L.n, N, 4, 4))  # T_base at each corrected home frame (before its motion)
        Ws = np.empty((L.n, N, 4, 4))  # ... and after it
        T = np.broadcast_to(np.eye(4), (N, 4, 4))
        for k in range(L.n):
            Fs[k] = T @ rel[k]
            Ws[k] = T = Fs[k] @ M[:, k]
        T = T @ L.tail
        R = T[:, :3, :3]
        p = np.einsum("nij,nj->ni", R, pf) + T[:, :3, 3]
        if not jac:
            return p, R, None
        tw = np.zeros((L.n, 1, 6, 6))
        tw[:, 0, :3, :3] = E.transpose(0, 2, 1)
        tw[:, 0, 3:, 3:] = so3_right_jacobian_many(r)
        cols = point_motion(Fs, tw, p)  # (n, N, 3, 6)
        cols[:-1] -= point_motion(Ws[:-1], tw[:-1], p)
        return p, R, np.ascontiguousarray(cols.transpose(1, 2, 0, 3).reshape(N, 3, 6 * L.n))
