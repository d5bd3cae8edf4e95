"""Serial kinematic chain: batched forward kinematics and the geometric Jacobian.

A chain from ``base`` to ``tip`` is the URDF product

    T_base_tip(q) = prod_k [ T_parent_joint_k @ M_k(q_k) ]

over its joints in order, with ``M_k = Rot(axis_k, q_k)`` for a revolute joint,
``Trans(axis_k * q_k)`` for a prismatic one and the identity for a fixed one.
Fixed joints are folded into the constant transform in front of the next
actuated joint, so evaluation costs one batched ``4 x 4`` product per actuated
joint.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64, matrix_from_axis_angle
from pipeline.kinematics.urdf import (
    Inertial,
    Joint,
    RobotDescription,
    carried_inertials,
    chain_joints,
    parse_urdf,
)


@dataclass(frozen=True)
class Chain:
    """Serial chain between two links.

    Attributes
    ----------
    base_link, tip_link : str
    joints : tuple of Joint
        Every joint on the way (fixed ones included), base first.
    inertials : dict of str to Inertial
        Mass and centre of mass each link below the base carries rigidly (its
        own ``<inertial>`` and the off-chain bodies hanging off it, see
        :func:`pipeline.kinematics.urdf.carried_inertials`), keyed by link name;
        empty when the URDF has no inertials.
    """

    base_link: str
    tip_link: str
    joints: tuple[Joint, ...]
    inertials: Mapping[str, Inertial] = field(default_factory=dict, repr=False, compare=False)
    _segments: tuple[F64, ...] = field(init=False, repr=False, compare=False)
    _tail: F64 = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        segs: list[F64] = []
        acc = np.eye(4)
        for j in self.joints:
            acc = acc @ j.T_parent_joint
            if j.actuated:
                segs.append(acc)
                acc = np.eye(4)
        object.__setattr__(self, "_segments", tuple(segs))
        object.__setattr__(self, "_tail", acc)

    @property
    def actuated(self) -> tuple[Joint, ...]:
        """The joints that move, in chain order."""
        return tuple(j for j in self.joints if j.actuated)

    @property
    def joint_names(self) -> list[str]:
        """Names of the actuated joints: the columns of a joint vector ``q``."""
        return [j.name for j in self.actuated]

    @property
    def n_dof(self) -> int:
        return len(self._segments)

    @property
    def lower(self) -> F64:
        return np.array([j.lower for j in self.actuated])

    @property
    def upper(self) -> F64:
        return np.array([j.upper for j in self.actuated])

    def with_origins(self, origins: Mapping[str, F64]) -> Chain:
        """A copy whose named joints have new ``T_parent_joint`` origins."""
        unknown = set(origins) - {j.name for j in self.joints}
        if unknown:
            raise KeyError(f"joints not in chain: {sorted(unknown)}")
        joints = tuple(
            replace(j, T_parent_joint=np.asarray(origins[j.name], dtype=float))
            if j.name in origins
            else j
            for j in self.joints
        )
        return Chain(self.base_link, self.tip_link, joints, self.inertials)

    def with_tip(self, T_tip_extra: F64, name: str = "tool") -> Chain:
        """A copy extended by a fixed transform after the tip (e.g. a tool)."""
        j = Joint(
            name=f"{name}_joint",
            type="fixed",
            parent=self.tip_link,
            child=name,
            T_parent_joint=np.asarray(T_tip_extra, dtype=float),
            axis=np.zeros(3),
        )
        return Chain(self.base_link, name, self.joints + (j,), self.inertials)


def load_chain(urdf: str | RobotDescription, base_link: str, tip_link: str) -> Chain:
    """Build the chain from ``base_link`` to ``tip_link`` of a URDF (XML text or parsed)."""
    robot = parse_urdf(urdf) if isinstance(urdf, str) else urdf
    path = chain_joints(robot, base_link, tip_link)
    return Chain(base_link, tip_link, tuple(path), carried_inertials(robot, path))


def _motion(joint: Joint, qk: F64) -> F64:
    """``M_k(q_k)`` for a batch of joint positions: ``(N,) -> (N, 4, 4)``."""
    M = np.zeros(qk.shape + (4, 4))
    M[..., 3, 3] = 1.0
    if joint.type == "prismatic":
        M[..., 0, 0] = M[..., 1, 1] = M[..., 2, 2] = 1.0
        M[..., :3, 3] = qk[..., None] * joint.axis
    else:
        M[..., :3, :3] = matrix_from_axis_angle(joint.axis, qk)
    return M


def _rmul_const(T: F64, C: F64) -> F64:
    """``T @ C`` for a batch ``T (N, 4, 4)`` and one constant ``C (4, 4)``, as one GEMM."""
    N = T.shape[0]
    return (np.ascontiguousarray(T).reshape(N * 4, 4) @ C).reshape(N, 4, 4)


def _apply_motion(T: F64, joint: Joint, qk: F64) -> F64:
    """``T @ M_k(q_k)`` without forming ``M_k``: ``(N, 4, 4), (N,) -> (N, 4, 4)``.

    Revolute: ``T @ Rot(a, q) = T + sin(q) (T K) + (1 - cos(q)) (T K^2)`` with the
    constant ``K = [a]_x`` padded to ``4 x 4`` (Rodrigues), so both products are
    single GEMMs against constants. Prismatic: ``t += q R a``.
    """
    if joint.type == "prismatic":
        out = T.copy()
        out[:, :3, 3] += qk[:, None] * (T[:, :3, :3] @ joint.axis)
        return out
    a = joint.axis
    K = np.zeros((4, 4))
    K[:3, :3] = [[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]]
    return (
        T
        + np.sin(qk)[:, None, None] * _rmul_const(T, K)
        + (1.0 - np.cos(qk))[:, None, None] * _rmul_const(T, K @ K)
    )


def _as_batch(chain: Chain, q: ArrayLike) -> tuple[F64, bool]:
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    q2 = q[None, :] if single else q
    if q2.ndim != 2 or q2.shape[1] != chain.n_dof:
        raise ValueError(f"q must be (N, {chain.n_dof}) or ({chain.n_dof},), got {q.shape}")
    return q2, single


def fk(chain: Chain, q: ArrayLike) -> F64:
    """Forward kinematics ``T_base_tip(q)``.

    Parameters
    ----------
    chain : Chain
    q : (N, n) or (n,)
        Joint positions (rad or m), columns in ``chain.joint_names`` order.

    Returns
    -------
    (N, 4, 4) or (4, 4)
    """
    q2, single = _as_batch(chain, q)
    T = np.broadcast_to(np.eye(4), (q2.shape[0], 4, 4))
    for k, (seg, joint) in enumerate(zip(chain._segments, chain.actuated, strict=True)):
        T = _apply_motion(_rmul_const(T, seg), joint, q2[:, k])
    T = _rmul_const(T, chain._tail)
    return T[0] if single else T


def fk_frames(chain: Chain, q: ArrayLike) -> tuple[F64, F64]:
    """Forward kinematics with every actuated joint's frame.

    Returns
    -------
    T_base_tip : (N, 4, 4)
    T_base_joint : (N, n, 4, 4)
        Frame of joint ``k`` (after its origin, before its motion; the joint
        axis is ``T_base_joint[:, k, :3, :3] @ axis_k`` through its origin).
    """
    q2, _ = _as_batch(chain, q)
    N = q2.shape[0]
    frames = np.empty((N, chain.n_dof, 4, 4))
    T = np.broadcast_to(np.eye(4), (N, 4, 4))
    for k, (seg, joint) in enumerate(zip(chain._segments, chain.actuated, strict=True)):
        T = _rmul_const(T, seg)
        frames[:, k] = T
        T = _apply_motion(T, joint, q2[:, k])
    return _rmul_const(T, chain._tail), frames


def jacobian(chain: Chain, q: ArrayLike, p_tip_point: ArrayLike | None = None) -> F64:
    """Geometric Jacobian of a point fixed in the tip frame, in the base frame.

    For revolute joint ``k`` with base-frame axis ``z_k`` through ``o_k``:
    ``J_v = z_k x (p - o_k)``, ``J_w = z_k``; prismatic: ``J_v = z_k``,
    ``J_w = 0``. So ``[dp; dtheta] = J @ dq`` (rows: linear xyz, angular xyz).

    Parameters
    ----------
    chain : Chain
    q : (N, n) or (n,)
    p_tip_point : (3,), optional
        Point in the tip frame (default: the tip origin).

    Returns
    -------
    (N, 6, n) or (6, n)
    """
    q2, single = _as_batch(chain, q)
    T_tip, frames = fk_frames(chain, q2)
    p_tip = np.zeros(3) if p_tip_point is None else np.asarray(p_tip_point, dtype=float)
    p = T_tip[:, :3, :3] @ p_tip + T_tip[:, :3, 3]
    J = np.zeros((q2.shape[0], 6, chain.n_dof))
    for k, joint in enumerate(chain.actuated):
        z = frames[:, k, :3, :3] @ joint.axis
        if joint.type == "prismatic":
            J[:, :3, k] = z
        else:
            J[:, :3, k] = np.cross(z, p - frames[:, k, :3, 3])
            J[:, 3:, k] = z
    return J[0] if single else J
