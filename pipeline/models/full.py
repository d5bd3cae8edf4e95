"""Full per-joint origin corrections: six per joint plus the joint zero offset.

Each actuated joint ``k`` gets

    origin_k' = Trans(xyz_k + d_k) @ R_k @ exp([r_k]) @ Rot(axis_k, dq0_k)

with ``xyz_k, R_k`` its nominal URDF origin, ``d_k`` (3, m) a translation in
the parent frame, ``r_k`` (3, rad) a rotation vector in the nominal joint
frame and ``dq0_k`` the zero offset (a translation along the axis for a
prismatic joint). This is the simulator's deviation model
(``origin(xyz + dxyz) @ RPY(drpy) @ Rot(axis, dq0)``) with the rotation in
exponential coordinates, so it represents any true robot of that kind
exactly. It is over-complete on purpose (the rotation about the axis and the
zero offset coincide, the first joint's origin is the base frame the targets
absorb, ...): identification keeps what the touch-ups identify (QR with column
pivoting) and holds the rest at nominal (``pipeline.stages.identify.stage``).

Jacobian, by equation (1) of :mod:`pipeline.models.base`: ``d_k`` is a pure
translation in frame ``X_k`` (the parent frame after the fixed joints before
``k``), ``r_k`` a rotation ``J_r(r_k) dr`` at frame ``Y_k = X_k Trans R_k
exp([r_k])``, ``dq0`` a rotation (translation) about (along) the axis at ``Y_k``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64
from pipeline.models.base import (
    ErrorModel,
    as_points,
    joint_motions,
    motion,
    point_motion,
    register,
    rotation,
    so3_exp,
    so3_exp_many,
    so3_right_jacobian_many,
    translation,
)

_I4 = np.eye(4)

COMPONENTS = ("dx", "dy", "dz", "rx", "ry", "rz", "dq0")
_UNITS = {"dx": "m", "dy": "m", "dz": "m", "rx": "rad", "ry": "rad", "rz": "rad", "dq0": "rad"}


@register
class FullOriginModel(ErrorModel):
    """Six origin corrections and a zero offset per joint (see module docstring)."""

    name = "full"
    description = "per-joint origin corrections (xyz, rotation vector) and zero offsets"
    components: tuple[str, ...] = COMPONENTS

    def __init__(self, chain: Chain) -> None:
        super().__init__(chain)
        L = self.layout
        self._slot: dict[tuple[int, str], int] = {}
        for k, jn in enumerate(L.names):
            for c in self.components:
                self._slot[(k, c)] = len(self.param_names)
                self.param_names.append(f"{jn}.{c}")
                self.param_joints.append(jn)
                unit = _UNITS[c]
                if c == "dq0" and L.prismatic[k]:
                    unit = "m"
                self.param_units.append(unit)
        self._k_idx = np.array([k for (k, _c) in self._slot], dtype=np.int64)
        self._c_idx = np.array([COMPONENTS.index(c) for (_k, c) in self._slot], dtype=np.int64)
        self._gather = 7 * self._k_idx + self._c_idx
        # among exactly dependent columns keep the zero offset (pivoting tie-break)
        self.param_priority = np.array(
            [1.05 if n.endswith(".dq0") else 1.0 for n in self.param_names]
        )

    def _unpack(self, x: ArrayLike) -> tuple[F64, F64, F64]:
        full = np.zeros((self.layout.n, 7))
        full[self._k_idx, self._c_idx] = np.asarray(x, dtype=float)
        return full[:, :3], full[:, 3:6], full[:, 6]

    def _fixed_part(self, k: int, d: F64, r: F64) -> F64:
        """``Trans(xyz + d) @ R @ exp([r])`` of joint ``k``."""
        o = self.layout.origin[k]
        return translation(o[:3, 3] + d) @ rotation(o[:3, :3] @ so3_exp(r))

    def origins(self, x: ArrayLike) -> dict[str, F64]:
        L = self.layout
        d, r, dq0 = self._unpack(x)
        out = {}
        for k, jn in enumerate(L.names):
            A = self._fixed_part(k, d[k], r[k])
            out[jn] = A @ motion(L.axis[k], bool(L.prismatic[k]), np.array([dq0[k]]))[0]
        return out

    def pin_and_jacobian(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
    ) -> tuple[F64, F64, F64 | None]:
        L = self.layout
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = q.shape[0]
        pf = as_points(p_flange, N)
        d, r, dq0 = self._unpack(x)
        # A_k = pre_k @ Trans(xyz_k + d_k) @ R_k @ exp([r_k]), all joints at once
        A = np.empty((L.n, 4, 4))
        A[:] = _I4
        A[:, :3, :3] = L.origin[:, :3, :3] @ so3_exp_many(r)
        A[:, :3, 3] = L.origin[:, :3, 3] + d
        A = L.pre @ A
        M = joint_motions(L.axis, L.prismatic, q + dq0)
        # T_base_{X_k} (before pre_k) and T_base_{Y_k} of every joint
        Ts = np.empty((L.n, N, 4, 4))
        Ys = np.empty((L.n, N, 4, 4))
        T = np.broadcast_to(_I4, (N, 4, 4))
        for k in range(L.n):
            Ts[k] = T
            Ys[k] = T @ A[k]
            T = Ys[k] @ M[:, k]
        T = T @ L.tail
        R = T[:, :3, :3]
        p = np.einsum("nij,nj->ni", R, pf) + T[:, :3, 3]
        if not jac:
            return p, R, None
        # all seven columns of every joint, then the model's subset in one gather
        blocks = np.empty((L.n, N, 3, 7))
        blocks[..., :3] = Ts[:, :, :3, :3] @ L.pre[:, None, :3, :3]
        tw = np.zeros((L.n, 6, 4))
        tw[:, 3:, :3] = so3_right_jacobian_many(r)
        tw[:, :3, 3] = np.where(L.prismatic[:, None], L.axis, 0.0)
        tw[:, 3:, 3] = np.where(L.prismatic[:, None], 0.0, L.axis)
        blocks[..., 3:] = point_motion(Ys, tw[:, None], p)
        J = blocks.transpose(1, 2, 0, 3).reshape(N, 3, 7 * L.n)[:, :, self._gather]
        return p, R, J
