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
    tau_j(q) = a_j . sum_{i: b_i >= j} (p_i(q) - o_j) x (m_i g)        (E2)
    p_base = FK_full(x_kin, q') @ p_flange                             (E3)

``c_j`` (rad/(N m)) is joint ``j``'s compliance, ``a_j`` and ``o_j`` its axis
and origin in the base frame, and the sum runs over the point masses ``m_i``
at ``p_i`` carried by the bodies at or beyond joint ``j`` (``b_i`` is the
actuated joint whose motion carries mass ``i``: the mass is fixed in the
frame of ``b_i``'s child link, ``B_b(q) = F_b(q) M_b(q_b)``, with ``F_b`` the
joint frame before its motion). ``g = (0, 0, -9.81) m/s^2``: gravity along
``-z`` of the base frame (the URDF convention for a floor-mounted robot; a
wall- or ceiling-mounted base would need its own direction, which neither the
URDF nor the touch-up table says). ``FK_full`` is
:class:`pipeline.models.full.FullOriginModel`. In the sum's closed form,
with ``M_j = sum_{b_i >= j} m_i`` and ``S_j = sum_{b_i >= j} m_i p_i``,

    tau_j(q) = a_j . ((S_j - M_j o_j) x g)                             (E5)

The mass model: a choice among registered candidates. What the masses are is
the one thing (E2) needs that the kinematics does not say. Each candidate is
its own registered error model, fixed a priori on physical grounds (see
:mod:`pipeline.models.elastic_mass` for the other two), and a run chooses
among them by held-out error like among any error models:

* ``elastic`` (this module, :class:`ElasticModel`): lumped masses, one equal
  ``m = 1 kg`` at the origin of every actuated joint's frame and one at the
  tip (flange) link's origin: the motors and joint housings, where much of a
  light arm's mass sits;
* ``elastic_mid``: one equal 1 kg mass at the mid-point of every link
  segment (joint origin to the next joint's origin, the last to the tip):
  the centre of a uniform link;
* ``elastic_inertial``: the URDF's own ``<inertial>`` masses and centres of
  mass, per link (offered only when the URDF has them).

For a lumped model only the *shape* of ``tau_j(q)`` over the poses matters to
the fit: a common factor on every mass rescales ``c_j`` alone. So ``c_j`` is
the compliance per newton-metre of *that* lumped model's torque (with 1 kg
masses), not a physical stiffness; it is physical only when the masses are
(``elastic_inertial`` with a URDF whose inertials are the arm's).

The regressor is evaluated on the *nominal* chain at the encoder angles ``q``
(not the corrected chain at ``q'``): the difference is second order in the
corrections and keeps ``tau`` independent of ``x``. A mass on joint ``j``'s
axis exerts no torque about it; a joint whose torque vanishes everywhere (a
vertical first axis) has a zero column that identification holds as
unidentifiable. Prismatic joints get no compliance.

Payload. A payload of ``m_p`` kg with its centre of mass at ``c_p`` in the
flange (tip link) frame is one more point mass on the last body:

    tau_j(q; m_p) = tau_j(q) + a_j . ((T_tip(q) c_p - o_j) x (m_p g))   (E6)

:meth:`ElasticModel.set_payload` fixes the payload every later evaluation
assumes (a fit, then predictions; identification fits without one, 0 kg, and
:meth:`ElasticModel.mass_model` reports the payload the instance assumes);
:meth:`ElasticModel.predict` and :meth:`ElasticModel.torque` also take one
mass per row (``payload_kg``). The deflection a payload adds is ``c_j`` times
(E6)'s extra torque in newton-metres. That is physical only with physical
masses: with a lumped model the identified ``c_j`` absorbed the unknown
ratio between the lumped and the real arm's torque, so a payload's predicted
deflection is off by that unknown factor (and by the shape the lumped
masses get wrong); it is a guess in the right direction, not a prediction.

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

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain, fk_frames
from pipeline.kinematics.se3 import F64
from pipeline.models.base import ChainLayout, joint_motions, register
from pipeline.models.full import FullOriginModel

#: gravity in the base frame, m/s^2 (floor-mounted base: -z)
G_BASE = np.array([0.0, 0.0, -9.81])
#: the lumped mass at every actuated joint frame and at the tip, kg (see module docstring)
LUMPED_MASS_KG = 1.0
COMPLIANCE_UNIT = "rad/(N m)"


@dataclass(frozen=True)
class PointMasses:
    """The point masses of (E2), each fixed to one body of the chain.

    Attributes
    ----------
    body : (M,) int
        The actuated joint (index in the chain's order) whose child link frame
        ``B_b(q) = F_b(q) M_b(q_b)`` carries the mass; ``-1``: the base (no torque).
    mass : (M,) kg
    pos : (M, 3) position in that frame, m
    labels : (M,) what each mass stands for (for :meth:`ElasticModel.mass_model`)
    """

    body: np.ndarray
    mass: F64
    pos: F64
    labels: tuple[str, ...]

    @property
    def total(self) -> float:
        return float(self.mass.sum())


def lumped_masses(layout: ChainLayout, mass_kg: float = LUMPED_MASS_KG) -> PointMasses:
    """``elastic``'s masses: ``mass_kg`` at every actuated joint origin and at the tip.

    Joint ``k``'s origin is fixed to the body before it (``k - 1``; the base for
    ``k = 0``) at that body's segment ``pre_k @ origin_k``; the tip's to the last
    body at ``tail``. A revolute joint's origin is the same point before and after
    its motion, so (E2) with these masses is the classic "masses beyond joint j".
    """
    n = layout.n
    seg = layout.pre @ layout.origin  # (n, 4, 4): joint k's frame in body k - 1's
    body = np.arange(-1, n)
    pos = np.concatenate([seg[:, :3, 3], layout.tail[None, :3, 3]])
    labels = (*(f"{k} origin" for k in layout.names), "tip origin")
    return PointMasses(body, np.full(n + 1, float(mass_kg)), pos, labels)


def body_frames(chain: Chain, layout: ChainLayout, q: F64) -> tuple[F64, F64, F64]:
    """Base-frame poses the torque needs, from the nominal chain at ``q`` (N, n).

    Returns
    -------
    T_tip : (N, 4, 4) the tip (flange) link
    F : (N, n, 4, 4) joint frames before their motion (axis ``F[..., :3, :3] @ a_k``
        through ``F[..., :3, 3]``)
    B : (N, n, 4, 4) joint ``k``'s child link frame after its motion, ``F_k M_k(q_k)``
    """
    T_tip, F = fk_frames(chain, q)
    B = F @ joint_motions(layout.axis, layout.prismatic, q)
    return T_tip, F, B


def torque_of(
    masses: PointMasses,
    layout: ChainLayout,
    frames: tuple[F64, F64, F64],
    payload_kg: F64 | None = None,
    payload_com: F64 | None = None,
) -> F64:
    """Equations (E5)-(E6): gravity torque about every actuated joint, (N, n) N m.

    Parameters
    ----------
    masses : the point masses (see :class:`PointMasses`)
    layout : the chain's layout (axes, prismatic flags)
    frames : :func:`body_frames` at the joint vectors
    payload_kg : (N,) payload per row, kg, or None
    payload_com : (3,) its centre of mass in the tip frame, m (default the tip origin)

    Prismatic joints get 0.
    """
    T_tip, F, B = frames
    N, n = F.shape[:2]
    S = np.zeros((N, n, 3))  # first moment m p per body, then summed beyond
    M = np.zeros(n)
    for b, m, p in zip(masses.body, masses.mass, masses.pos, strict=True):
        if b < 0 or m == 0.0:
            continue
        S[:, b] += m * (B[:, b, :3, :3] @ p + B[:, b, :3, 3])
        M[b] += m
    S = np.cumsum(S[:, ::-1], axis=1)[:, ::-1]  # S_j = sum over bodies >= j
    Mj = np.broadcast_to(np.cumsum(M[::-1])[::-1], (N, n)).copy()
    if payload_kg is not None:
        c = np.zeros(3) if payload_com is None else np.asarray(payload_com, dtype=float)
        pw = T_tip[:, :3, :3] @ c + T_tip[:, :3, 3]  # (N, 3)
        S += (payload_kg[:, None] * pw)[:, None, :]
        Mj += payload_kg[:, None]
    o = F[:, :, :3, 3]
    a = np.einsum("nkij,kj->nki", F[:, :, :3, :3], layout.axis)
    tau = np.einsum("nki,nki->nk", a, np.cross(S - Mj[..., None] * o, G_BASE))
    tau[:, layout.prismatic] = 0.0
    return tau


def gravity_torque(chain: Chain, q: ArrayLike) -> F64:
    """Equation (E2): gravity torque about each actuated joint of ``elastic``'s lumped-mass arm.

    Parameters
    ----------
    chain : the nominal chain (base link to tip link)
    q : (N, n) joint vectors

    Returns
    -------
    (N, n) torque about each joint axis, N m (zero for prismatic joints).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    layout = ChainLayout.from_chain(chain)
    return torque_of(lumped_masses(layout), layout, body_frames(chain, layout, q))


@register
class ElasticModel(FullOriginModel):
    """``full`` plus one gravity-torque compliance per revolute joint (see module docstring).

    Subclasses choose the mass model by overriding :meth:`point_masses` (and
    ``mass_kind``, ``masses_physical``); everything else is shared.

    Attributes
    ----------
    n_kin : the number of ``full`` parameters (the compliances follow them)
    elastic_joints : (n_revolute,) indices of the joints with a compliance
    masses : the :class:`PointMasses` of (E2)
    payload_kg, payload_com : the payload :meth:`set_payload` set (0 kg at the tip origin)
    """

    name = "elastic"
    description = (
        "per-joint origin corrections and zero offsets plus a compliance per revolute joint "
        "on the gravity torque of a lumped-mass arm (1 kg at each joint and the tip; "
        "the URDF carries the rigid part only)"
    )
    #: a URDF cannot carry the configuration-dependent deflection
    urdf_exact = False
    #: ``mass_model()["kind"]``
    mass_kind = "lumped_joint_origins"
    #: the masses are the arm's physical ones (a payload then predicts physically)
    masses_physical = False

    def __init__(self, chain: Chain) -> None:
        super().__init__(chain)
        L = self.layout
        self.masses = self.point_masses(chain)
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
        self.payload_kg = 0.0
        self.payload_com = np.zeros(3)
        self._tau_last: tuple[F64, F64] | None = None  # (q, torque) of _elastic_torque

    def point_masses(self, chain: Chain) -> PointMasses:
        """The mass model of (E2): here ``elastic``'s lumped masses (:func:`lumped_masses`)."""
        return lumped_masses(self.layout)

    def set_payload(self, mass_kg: float, p_flange_com: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """Assume a payload of ``mass_kg`` at ``p_flange_com`` (m, flange frame) from now on.

        Every later :meth:`pin_and_jacobian`, :meth:`deflection`, :meth:`torque` and
        :meth:`predict` adds its torque (E6). Physical only with physical masses
        (see the module docstring); ``set_payload(0.0)`` removes it.
        """
        mass = float(mass_kg)
        com = np.asarray(p_flange_com, dtype=float).reshape(3)
        if not np.isfinite(mass) or mass < 0 or not np.all(np.isfinite(com)):
            raise ValueError(f"payload {mass_kg!r} kg at {p_flange_com!r}: need a finite mass >= 0")
        self.payload_kg, self.payload_com = mass, com
        self._tau_last = None

    def torque(self, q: ArrayLike, payload_kg: ArrayLike | None = None) -> F64:
        """Equations (E5)-(E6) on the nominal arm: (N, n) N m, 0 for prismatic joints.

        ``payload_kg``: None for the payload :meth:`set_payload` set, else a mass
        (kg) or one per row (N,), at the set payload's centre of mass.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        N = len(q)
        mp = self.payload_kg if payload_kg is None else payload_kg
        mp_rows = np.broadcast_to(np.asarray(mp, dtype=float), (N,))
        frames = body_frames(self.nominal, self.layout, q)
        has = bool(np.any(mp_rows != 0))
        return torque_of(
            self.masses,
            self.layout,
            frames,
            mp_rows if has else None,
            self.payload_com if has else None,
        )

    def mass_model(self) -> dict[str, Any]:
        """The mass model (E2) and payload this instance assumes, JSON-serialisable.

        Keys: ``model``, ``kind``, ``physical`` (the compliances are per physical
        N m), ``gravity_m_s2`` (base frame), ``masses`` (one dict per point mass:
        ``label``, ``body`` (the joint whose child link frame holds it, or
        ``"base"``), ``mass_kg``, ``position_m`` in that frame), ``total_kg`` and
        ``payload`` (``mass_kg``, ``com_flange_m``: the payload assumed; read after
        identification, the one the fit assumed, 0 kg unless set before it).
        """
        names = self.layout.names
        m = self.masses
        return {
            "model": self.name,
            "kind": self.mass_kind,
            "physical": bool(self.masses_physical),
            "gravity_m_s2": [float(v) for v in G_BASE],
            "masses": [
                {
                    "label": lab,
                    "body": names[int(b)] if b >= 0 else "base",
                    "mass_kg": float(mk),
                    "position_m": [float(v) for v in p],
                }
                for b, mk, p, lab in zip(m.body, m.mass, m.pos, m.labels, strict=True)
            ],
            "total_kg": m.total,
            "payload": {
                "mass_kg": float(self.payload_kg),
                "com_flange_m": [float(v) for v in self.payload_com],
            },
            "compliance_unit": COMPLIANCE_UNIT,
        }

    def column_scale(self, length: float) -> F64:
        """Metres a unit of each parameter moves the pin by, roughly (for scaling).

        Radians: the working radius ``length``; compliances: ``length`` times the
        arm's characteristic torque ``M |g| length`` (``M`` its total mass).
        """
        s = super().column_scale(length)
        mass = self.masses.total + self.payload_kg
        tau_ref = mass * float(np.linalg.norm(G_BASE)) * length
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
        tau = self.torque(q)[:, self.elastic_joints]
        self._tau_last = (q.copy(), tau)
        return tau

    def deflection(self, x: ArrayLike, q: ArrayLike, payload_kg: ArrayLike | None = None) -> F64:
        """Equation (E1)'s ``c_j tau_j(q)`` per pose and joint, (N, n) rad.

        ``payload_kg`` as in :meth:`torque`.
        """
        x = np.asarray(x, dtype=float)
        tau = self.torque(q, payload_kg)
        dq = np.zeros_like(tau)
        dq[:, self.elastic_joints] = tau[:, self.elastic_joints] * x[self.n_kin :]
        return dq

    def origins(self, x: ArrayLike) -> dict[str, F64]:
        """The rigid part only (a URDF cannot hold the deflection (E1))."""
        return super().origins(np.asarray(x, dtype=float)[: self.n_kin])

    def predict(
        self, x: ArrayLike, q: ArrayLike, p_flange: ArrayLike, payload_kg: ArrayLike | None = None
    ) -> F64:
        """(E3) with a payload per row: pins in the base frame, (N, 3).

        ``payload_kg``: None for the payload :meth:`set_payload` set, else a mass
        (kg) or one per row (N,), at the set payload's centre of mass.
        """
        self.check_inputs(x, q, p_flange)
        x = np.asarray(x, dtype=float)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        qd = q + self.deflection(x, q, payload_kg)
        return FullOriginModel.pin_and_jacobian(self, x[: self.n_kin], qd, p_flange, jac=False)[0]

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
