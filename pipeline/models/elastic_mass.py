"""The other mass models of the elastic error model: link mid-points and the URDF's inertials.

:mod:`pipeline.models.elastic` defines the model (equations (E1)-(E6)) and its
lumped candidate ``elastic``; this module registers the two others. Each is a
hypothesis about where the arm's weight sits, fixed before any data is seen:

* ``elastic_mid`` (:class:`ElasticMidModel`): one 1 kg mass at the mid-point of
  every kinematic segment of the nominal chain,

      p_k = (1/2) t_k   in the frame of joint k's child link B_k          (M1)

  with ``t_k`` the translation from joint ``k``'s origin to joint ``k + 1``'s
  (``pre_{k+1} @ origin_{k+1}``), and for the last joint to the tip link's
  origin (``tail``). A link of uniform density along its segment has its centre
  of mass there; the masses are equal, as ``elastic``'s, so the two differ in
  where the weight sits only. A zero-length segment (two joint axes through one
  point, e.g. the Panda's joints 1-2 and 5-6) puts its mass on the joint.
  Lumped and non-physical: ``c_j`` is per newton-metre of this model's torque.

* ``elastic_inertial`` (:class:`ElasticInertialModel`): the URDF's
  ``<inertial>`` elements, per link,

      m_L, p_L = T_{B_b L} c_L   in the frame of the last actuated joint
                                 b before link L (its child link B_b)     (M2)

  with ``T_{B_b L}`` the fixed joints from ``B_b`` to link ``L`` and ``c_L``
  the ``<inertial><origin xyz>``; a link's off-chain subtree (fingers, a tool
  beyond the tip) is merged into it at zero joint positions
  (:func:`pipeline.kinematics.urdf.carried_inertials`). Physical: with the
  arm's true masses ``c_j`` is a compliance in rad/(N m) and a payload
  predicts physically. Offered only for a URDF that has inertials: on one
  without, constructing it raises :class:`pipeline.errors.BadInput` saying so
  (a run's ``--model all`` reports it among the models that failed).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import BadInput
from pipeline.kinematics.chain import Chain
from pipeline.models.base import register
from pipeline.models.elastic import LUMPED_MASS_KG, ElasticModel, PointMasses


def midpoint_masses(model: ElasticModel, mass_kg: float = LUMPED_MASS_KG) -> PointMasses:
    """Equation (M1): ``mass_kg`` at the mid-point of every segment, on body ``k``."""
    L = model.layout
    seg = L.pre @ L.origin  # joint k's frame in body k - 1's
    ends = np.concatenate([seg[1:, :3, 3], L.tail[None, :3, 3]])  # body k's far end
    names = L.names
    labels = tuple(f"mid {names[k]}-{names[k + 1] if k + 1 < L.n else 'tip'}" for k in range(L.n))
    return PointMasses(np.arange(L.n), np.full(L.n, float(mass_kg)), 0.5 * ends, labels)


def inertial_masses(chain: Chain) -> PointMasses:
    """Equation (M2): the chain's link inertials, each on the body that carries it.

    Raises
    ------
    BadInput
        If the chain carries no inertial, or none beyond its first actuated joint.
    """
    if not chain.inertials:
        raise BadInput(
            "error model 'elastic_inertial': the URDF has no <inertial> elements on the "
            f"chain {chain.base_link} -> {chain.tip_link}; use elastic or elastic_mid"
        )
    body, mass, pos, labels = [], [], [], []
    b = -1
    T = np.eye(4)  # the current link's frame in body b's
    for j in chain.joints:
        if j.actuated:
            b += 1
            T = np.eye(4)
        else:
            T = T @ j.T_parent_joint
        inertial = chain.inertials.get(j.child)
        if inertial is not None and inertial.mass > 0:
            body.append(b)
            mass.append(inertial.mass)
            pos.append(T[:3, :3] @ inertial.com + T[:3, 3])
            labels.append(j.child)
    if not any(bb >= 0 for bb in body):
        raise BadInput(
            "error model 'elastic_inertial': no link beyond the first joint of "
            f"{chain.base_link} -> {chain.tip_link} has an <inertial> mass"
        )
    return PointMasses(np.array(body, dtype=np.int64), np.array(mass), np.array(pos), tuple(labels))


@register
class ElasticMidModel(ElasticModel):
    """``elastic`` with 1 kg at every link segment's mid-point (M1) (see module docstring)."""

    name = "elastic_mid"
    description = (
        "elastic with its lumped 1 kg masses at the link mid-points instead of the joints "
        "(the URDF carries the rigid part only)"
    )
    mass_kind = "lumped_link_midpoints"
    masses_physical = False

    def point_masses(self, chain: Chain) -> PointMasses:
        return midpoint_masses(self)


@register
class ElasticInertialModel(ElasticModel):
    """``elastic`` on the URDF's per-link masses and centres of mass (M2) (see module docstring)."""

    name = "elastic_inertial"
    description = (
        "elastic on the gravity torque of the URDF's <inertial> link masses and centres of "
        "mass (only for a URDF that has them; the URDF carries the rigid part only)"
    )
    mass_kind = "urdf_inertials"
    masses_physical = True

    @classmethod
    def applies(cls, chain: Chain) -> bool:
        """Only on a chain whose URDF gives link inertials."""
        return bool(getattr(chain, "inertials", None))

    def point_masses(self, chain: Chain) -> PointMasses:
        return inertial_masses(chain)
