"""Modified Denavit-Hartenberg with Hayati's parameter on (nearly) parallel axes.

Craig's modified DH (1986) link transform from joint frame ``i-1`` to ``i``

    L_i = Rx(alpha_i) Tx(a_i) Rz(theta_i) Tz(d_i)

is singular when axes ``i-1`` and ``i`` are parallel: a small tilt moves the
common normal arbitrarily far and ``d_i`` jumps (the metres-off ``d`` values
naive DH calibrations report). There, Hayati & Mirmirani (1985) replace
``d_i`` by a rotation ``beta_i`` about ``y``:

    L_i = Rx(alpha_i) Ry(beta_i) Tx(a_i) Rz(theta_i) Tz(d_i),  d_i held constant.

``T_base_flange(q) = B prod_i [E_i L_i Rz(q_i)] T_n_flange`` with ``B`` the
first joint's frame at home and ``E_i`` a constant (identity for a URDF whose
nearly parallel axes are exactly parallel) that makes the nominal product
reproduce the URDF exactly. MDH frames are built from the home axis lines:
``z`` along the URDF axis, the origin on the axis at the foot of the common
normal to the next axis, ``x`` along that normal. Four parameters per joint
(``alpha, a, theta, d`` or ``alpha, beta, a, theta``), ``theta`` being the
zero offset. Revolute joints only.

URDF write-back is exact: with ``C_i`` the constant map from URDF joint frame
``i`` to MDH frame ``i`` (a rotation taking the URDF axis to ``z`` and a shift
along it, so it commutes with the joint motion),
``origin_i' = pre_i^{-1} C_{i-1}^{-1} E_i L_i' C_i`` (``C_{-1}^{-1} = B``).

Jacobian, by equation (1) of :mod:`pipeline.models.base`: each factor's
derivative is a unit twist at the frame just before it (``alpha``: ``w = x``,
``beta``: ``w = y``, ``a``: ``v = x``, ``theta``: ``w = z``, ``d``: ``v = z``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.errors import BadInput
from pipeline.kinematics.chain import Chain, fk, fk_frames
from pipeline.kinematics.se3 import F64, invert_transform, matrix_from_axis_angle
from pipeline.models.base import ErrorModel, as_points, joint_motions, point_motion, register

_EX, _EY, _EZ = np.eye(3)


def _rx(t: float) -> F64:
    T = np.eye(4)
    T[:3, :3] = matrix_from_axis_angle(_EX, t)
    return T


def _ry(t: float) -> F64:
    T = np.eye(4)
    T[:3, :3] = matrix_from_axis_angle(_EY, t)
    return T


def _rz(t: float) -> F64:
    T = np.eye(4)
    T[:3, :3] = matrix_from_axis_angle(_EZ, t)
    return T


def _tx(s: float) -> F64:
    T = np.eye(4)
    T[0, 3] = s
    return T


def _tz(s: float) -> F64:
    T = np.eye(4)
    T[2, 3] = s
    return T


def _perp(v: F64, z: F64) -> F64 | None:
    """Unit component of ``v`` perpendicular to unit ``z`` (None if ~0)."""
    w = v - z * (v @ z)
    nw = float(np.linalg.norm(w))
    return w / nw if nw > 1e-9 else None


def _any_perp(z: F64) -> F64:
    e = _EX if abs(z[0]) < 0.9 else _EY
    w = _perp(e, z)
    assert w is not None
    return w


def mdh_frames(z: F64, o: F64, parallel: np.ndarray) -> F64:
    """MDH frames ``(n, 4, 4)`` from home axis lines ``z`` (n, 3), points ``o`` (n, 3)."""
    n = len(z)
    out = np.zeros((n, 4, 4))
    prev_o, prev_x = o[0], None
    for i in range(n):
        zi = z[i]
        p0 = o[i] + zi * ((prev_o - o[i]) @ zi)  # foot of the previous normal
        x: F64 | None = None
        origin = p0
        if i < n - 1 and not parallel[i + 1]:
            zj, oj = z[i + 1], o[i + 1]
            b = zi @ zj
            w0 = o[i] - oj
            den = 1.0 - b * b
            ti = (b * (zj @ w0) - zi @ w0) / den
            tj = ((zj @ w0) - b * (zi @ w0)) / den
            pi, pj = o[i] + ti * zi, oj + tj * zj
            origin = pi
            x = _perp(pj - pi, zi)
            if x is None:  # intersecting axes
                c = np.cross(zi, zj)
                x = c / np.linalg.norm(c)
        elif i < n - 1:  # parallel: perpendicular towards the next axis
            x = _perp(o[i + 1] - p0, zi)
        if x is None:
            x = _perp(prev_x, zi) if prev_x is not None else None
        if x is None:
            x = _any_perp(zi)
        y = np.cross(zi, x)
        out[i, :3, 0], out[i, :3, 1], out[i, :3, 2], out[i, :3, 3] = x, y, zi, origin
        out[i, 3, 3] = 1.0
        prev_o, prev_x = origin, x
    return out


@register
class MDHModel(ErrorModel):
    """Modified DH with Hayati's ``beta`` where consecutive axes are (nearly) parallel."""

    name = "mdh"
    description = "modified DH, Hayati's beta on (nearly) parallel consecutive axes"
    parallel_tol = 0.01  # rad: axes closer than this to parallel get Hayati's beta

    def __init__(self, chain: Chain) -> None:
        super().__init__(chain)
        L = self.layout
        if L.prismatic.any():
            jn = L.names[int(np.argmax(L.prismatic))]
            raise BadInput(f"error model mdh: joint {jn!r} is prismatic; use full, poe or offsets")
        n = L.n
        _, frames = fk_frames(chain, np.zeros(n))
        G = frames[0]
        z = np.einsum("nij,nj->ni", G[:, :3, :3], L.axis)
        o = G[:, :3, 3]
        parallel = np.zeros(n, dtype=bool)
        for i in range(1, n):
            parallel[i] = np.linalg.norm(np.cross(z[i - 1], z[i])) < np.sin(self.parallel_tol)
        self.hayati = parallel
        Mf = mdh_frames(z, o, parallel)
        self.B = Mf[0]
        self.C = invert_transform(Mf) @ G  # URDF joint frame in MDH frame
        self.C_inv = invert_transform(self.C)
        self.T_n_flange = invert_transform(Mf[-1]) @ fk(chain, np.zeros(n))
        self._pre_inv = invert_transform(L.pre)
        # nominal (alpha, beta, a, theta, d) and the constant E_i
        self.nom = np.zeros((n, 5))
        self.E = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        for i in range(1, n):
            Trel = invert_transform(Mf[i - 1]) @ Mf[i]
            zz = Trel[:3, 2]
            beta = float(np.arcsin(np.clip(zz[0], -1, 1))) if parallel[i] else 0.0
            alpha = float(np.arctan2(-zz[1], zz[2]))
            Rxy = (_rx(alpha) @ _ry(beta))[:3, :3]
            Rz = Rxy.T @ Trel[:3, :3]
            theta = float(np.arctan2(Rz[1, 0], Rz[0, 0]))
            pl = Rxy.T @ Trel[:3, 3]
            self.nom[i] = (alpha, beta, pl[0], theta, pl[2])
            self.E[i] = Trel @ invert_transform(self._link(i, self.nom[i]))
        self._slots: list[tuple[int, int]] = []  # (joint, index into alpha,beta,a,theta,d)
        names = ("alpha", "beta", "a", "theta", "d")
        for i, jn in enumerate(L.names):
            comps = (0, 1, 2, 3) if parallel[i] else (0, 2, 3, 4)
            for c in comps:
                self._slots.append((i, c))
                self.param_names.append(f"{jn}.{names[c]}")
                self.param_joints.append(jn)
                self.param_units.append("m" if names[c] in ("a", "d") else "rad")
        self.param_nominal = [float(self.nom[i, c]) for i, c in self._slots]
        # each parameter's unit twist at the frame just before its factor (P, 1, 6, 1)
        unit = {0: (3, _EX), 1: (3, _EY), 2: (0, _EX), 3: (3, _EZ), 4: (0, _EZ)}
        self._slot_joint = np.array([i for i, _c in self._slots], dtype=np.int64)
        self._slot_comp = np.array([c for _i, c in self._slots], dtype=np.int64)
        self._slot_twist = np.zeros((len(self._slots), 1, 6, 1))
        for j, (_i, c) in enumerate(self._slots):
            off, e = unit[c]
            self._slot_twist[j, 0, off : off + 3, 0] = e
        self._axes_z = np.tile(_EZ, (n, 1))
        self._prismatic = np.zeros(n, dtype=bool)  # MDH: revolute joints only

    @staticmethod
    def _link(i: int, v: F64) -> F64:
        alpha, beta, a, theta, d = v
        return _rx(alpha) @ _ry(beta) @ _tx(a) @ _rz(theta) @ _tz(d)

    def _values(self, x: ArrayLike) -> F64:
        x = np.asarray(x, dtype=float)
        v = self.nom.copy()
        for j, (i, c) in enumerate(self._slots):
            v[i, c] += x[j]
        return v

    def origins(self, x: ArrayLike) -> dict[str, F64]:
        v = self._values(x)
        out = {}
        for i, jn in enumerate(self.layout.names):
            left = self.B if i == 0 else self.C_inv[i - 1]
            out[jn] = self._pre_inv[i] @ left @ self.E[i] @ self._link(i, v[i]) @ self.C[i]
        return out

    def _factors(self, v: F64) -> F64:
        """Cumulative products of every joint's link factors, (n, 6, 4, 4).

        ``A[i] = (E_i, E_i Rx, E_i Rx Ry, E_i Rx Ry Tx, E_i Rx Ry Tx Rz, E_i L_i)``:
        the frame just before parameter ``c`` of link ``i`` is ``T @ A[i, c]``.
        """
        n = self.layout.n
        F = np.empty((n, 5, 4, 4))
        F[:] = np.eye(4)
        F[:, 0, :3, :3] = matrix_from_axis_angle(_EX, v[:, 0])
        F[:, 1, :3, :3] = matrix_from_axis_angle(_EY, v[:, 1])
        F[:, 2, 0, 3] = v[:, 2]
        F[:, 3, :3, :3] = matrix_from_axis_angle(_EZ, v[:, 3])
        F[:, 4, 2, 3] = v[:, 4]
        A = np.empty((n, 6, 4, 4))
        A[:, 0] = self.E
        for c in range(5):
            A[:, c + 1] = A[:, c] @ F[:, c]
        return A

    def pin_and_jacobian(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
    ) -> tuple[F64, F64, F64 | None]:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N, n = q.shape
        pf = as_points(p_flange, N)
        A = self._factors(self._values(x))
        M = joint_motions(self._axes_z, self._prismatic, q)
        T = np.broadcast_to(self.B, (N, 4, 4))
        sites = np.empty((n, 5, N, 4, 4))
        for i in range(n):
            sites[i] = T @ A[i, :5, None]
            T = (T @ A[i, 5]) @ M[:, i]
        T = T @ self.T_n_flange
        R = T[:, :3, :3]
        p = np.einsum("nij,nj->ni", R, pf) + T[:, :3, 3]
        if not jac:
            return p, R, None
        sel = sites[self._slot_joint, self._slot_comp]  # (P, N, 4, 4)
        J = point_motion(sel, self._slot_twist, p)[..., 0].transpose(1, 2, 0)
        return p, R, np.ascontiguousarray(J)
