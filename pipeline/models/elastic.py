"""Joint elasticity: the ``full`` model plus a compliance per revolute joint.

A real arm's joints wind up under the load they carry: a harmonic drive or a
belt turns by a small angle proportional to the torque across it. Gravity is
the load of a slowly moving arm whose tool touches nothing, so the angle the
kinematics sees is the encoder's plus a deflection proportional to the gravity
torque at that joint (the classic joint-compliance term of robot calibration:
Whitney, Lozinski & Rourke 1986, "Industrial robot forward calibration method
and results", J. Dyn. Sys., Meas., Control 108(1); Gong, Yuan & Ni 2000,
"Nongeometric error identification and compensation for robotic system by
inverse calibration", Int. J. Mach. Tools Manuf. 40(14))::

    q'_j = q_j + c_j tau_j(q)                                          (E1)
    tau_j(q) = a_j . sum_{k distal to j} (p_k(q) - o_j) x (m_k g)      (E2)
    p_base = FK_full(x_kin, q') @ p_flange                             (E3)

``c_j`` (rad/(N m)) is joint ``j``'s compliance, ``a_j`` and ``o_j`` its axis
and origin in the base frame, ``p_k`` the lumped masses' positions and ``g =
(0, 0, -9.81) m/s^2``: gravity along ``-z`` of the base frame (the URDF
convention for a floor-mounted robot; a wall- or ceiling-mounted base would
need its own direction, which neither the URDF nor the touch-up table says).
``FK_full`` is :class:`pipeline.models.full.FullOriginModel`.

What is lumped, and why. vtcal's URDF reader carries no inertials (and the
datasets' URDFs have none), so the regressor (E2) is a declared lumped-mass
model, not an identified one: one equal mass ``m = 1 kg`` at the origin of
every actuated joint's frame and one at the tip (flange) link's origin. Only
the *shape* of ``tau_j(q)`` over the poses matters to the fit: a common
factor on every mass rescales ``c_j`` alone. So ``c_j`` is the compliance
per newton-metre of *this* lumped model's torque (with 1 kg masses), not a
physical stiffness; it is physical only when the masses are. The regressor
is evaluated on the *nominal* chain at the encoder angles ``q`` (not the
corrected chain at ``q'``): the difference is second order in the
corrections and keeps ``tau`` independent of ``x``. A mass at frame ``j``
lies on joint ``j``'s axis, so only masses beyond it count (E2); a joint whose
torque vanishes everywhere (a vertical first axis) has a zero column that
identification holds as unidentifiable. Prismatic joints get no compliance.

Jacobian (chain rule through ``q'``). The kinematic columns are ``full``'s at
``q'``. Since ``q'_j`` enters the product exactly as the zero offset
``dq0_j`` does (``Rot(a_j, q'_j + dq0_j)``),

    d p_base / d c_j = (d p_base / d dq0_j)(x_kin, q') * tau_j(q)      (E4)

per pose: ``full``'s zero-offset column (equation (1) of
:mod:`pipeline.models.base`: a rotation about ``a_j`` at joint ``j``) scaled by
that pose's torque. Shapes: ``q`` (N, n), ``tau`` (N, n), ``J`` (N, 3, P_full
+ n_revolute).

A URDF cannot hold (E1): :meth:`ElasticModel.origins` returns the rigid part
``x_kin`` only, which reproduces the model exactly only where ``tau = 0``.
``parameters.parquet`` and ``identify.json`` carry ``c_j``
(``JOINT.compliance``, unit ``rad/(N m)``); cross-validation predicts with the
full map (E3), and the shipped ``calibrated.urdf`` is never this model's
(``urdf_exact = False``; see :mod:`pipeline.stages.crossval.stage`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain, fk_frames
from pipeline.kinematics.se3 import F64
from pipeline.models.base import register
from pipeline.models.full import FullOriginModel

#: gravity in the base frame, m/s^2 (floor-mounted base: -z)
G_BASE = np.array([0.0, 0.0, -9.81])
#: the lumped mass at every actuated joint frame and at the tip, kg (see module docstring)
LUMPED_MASS_KG = 1.0
COMPLIANCE_UNIT = "rad/(N m)"


def gravity_torque(chain: Chain, q: ArrayLike) -> F64:
    """Equation (E2): gravity torque about each actuated joint of the lumped-mass arm.

    Parameters
    ----------
    chain : the nominal chain (base link to tip link)
    q : (N, n) joint vectors

    Returns
    -------
    (N, n) torque about each joint axis, N m (zero for prismatic joints).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    T_tip, F = fk_frames(chain, q)
    N, n = q.shape
    axes = np.array([j.axis for j in chain.actuated], dtype=float)  # (n, 3), joint frames
    a = np.einsum("nkij,kj->nki", F[:, :, :3, :3], axes)  # (N, n, 3) base-frame axes
    o = F[:, :, :3, 3]  # (N, n, 3) joint origins
    pts = np.concatenate([o, T_tip[:, None, :3, 3]], axis=1)  # (N, n + 1, 3) masses
    f = LUMPED_MASS_KG * G_BASE
    tau = np.zeros((N, n))
    for j, joint in enumerate(chain.actuated):
        if joint.type == "prismatic":
            continue
        lever = pts[:, j + 1 :] - o[:, j, None, :]  # masses beyond joint j
        moment = np.cross(lever, f).sum(axis=1)  # (N, 3)
        tau[:, j] = np.einsum("ni,ni->n", a[:, j], moment)
    return tau


@register
class ElasticModel(FullOriginModel):
    """``full`` plus one gravity-torque compliance per revolute joint (see module docstring)."""

    name = "elastic"
    description = (
        "per-joint origin corrections and zero offsets plus a compliance per revolute joint "
        "on the gravity torque of a lumped-mass arm (the URDF carries the rigid part only)"
    )
    #: a URDF cannot carry the configuration-dependent deflection
    urdf_exact = False

    def __init__(self, chain: Chain) -> None:
        super().__init__(chain)
        L = self.layout
        self.n_kin = len(self.param_names)
        self.elastic_joints = np.flatnonzero(~L.prismatic)
        self._dq0_cols = np.array([self._slot[(int(k), "dq0")] for k in self.elastic_joints])
        for k in self.elastic_joints:
            self.param_names.append(f"{L.names[k]}.compliance")
            self.param_joints.append(L.names[k])
            self.param_units.append(COMPLIANCE_UNIT)
        self.param_priority = np.concatenate(
            [self.param_priority, np.ones(len(self.elastic_joints))]
        )
        self._tau_last: tuple[F64, F64] | None = None  # (q, torque) of _elastic_torque

    def column_scale(self, length: float) -> F64:
        """Metres a unit of each parameter moves the pin by, roughly (for scaling).

        Radians: the working radius ``length``; compliances: ``length`` times the
        lumped arm's characteristic torque ``(n + 1) m |g| length``.
        """
        s = super().column_scale(length)
        tau_ref = (self.layout.n + 1) * LUMPED_MASS_KG * float(np.linalg.norm(G_BASE)) * length
        s[self.n_kin :] = length * tau_ref
        return s

    def _elastic_torque(self, q: F64) -> F64:
        """(E2)'s torque on the elastic joints, (N, n_elastic), kept for the last ``q``.

        A fit evaluates the model hundreds of times at the same joint vectors and
        the torque depends on them only (the nominal arm), so the last one is reused.
        """
        last = self._tau_last
        if last is not None and last[0].shape == q.shape and np.array_equal(last[0], q):
            return last[1]
        tau = gravity_torque(self.nominal, q)[:, self.elastic_joints]
        self._tau_last = (q.copy(), tau)
        return tau

    def deflection(self, x: ArrayLike, q: ArrayLike) -> F64:
        """Equation (E1)'s ``c_j tau_j(q)`` per pose and joint, (N, n) rad."""
        x = np.asarray(x, dtype=float)
        tau = gravity_torque(self.nominal, q)
        dq = np.zeros_like(tau)
        dq[:, self.elastic_joints] = tau[:, self.elastic_joints] * x[self.n_kin :]
        return dq

    def origins(self, x: ArrayLike) -> dict[str, F64]:
        """The rigid part only (a URDF cannot hold the deflection (E1))."""
        return super().origins(np.asarray(x, dtype=float)[: self.n_kin])

    def pin_and_jacobian(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, *, jac: bool = True
    ) -> tuple[F64, F64, F64 | None]:
        x = np.asarray(x, dtype=float)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        tau = self._elastic_torque(q)
        qd = q.copy()
        qd[:, self.elastic_joints] += tau * x[self.n_kin :]
        p, R, Jk = super().pin_and_jacobian(x[: self.n_kin], qd, p_flange, jac=jac)
        if Jk is None:
            return p, R, None
        Jc = Jk[:, :, self._dq0_cols] * tau[:, None, :]  # (E4)
        return p, R, np.concatenate([Jk, Jc], axis=2)
