"""Universal Robots kinematics YAML (``ur_description`` / the UR ROS drivers).

``ur_description`` builds a UR arm from one YAML file (launch argument
``kinematics_params_file``, xacro ``kinematics_parameters_file``)::

    kinematics:
      shoulder:  {x, y, z, roll, pitch, yaw}     # origin of shoulder_pan_joint
      upper_arm: {...}                           # shoulder_lift_joint
      forearm:   {...}                           # elbow_joint
      wrist_1:   {...}                           # wrist_1_joint
      wrist_2:   {...}                           # wrist_2_joint
      wrist_3:   {...}                           # wrist_3_joint
      hash: calib_...                            # checked against the controller's

and its xacro (``urdf/ur_macro.xacro``) composes them as URDF joint origins
(``R = Rz(yaw) Ry(pitch) Rx(roll)``), every joint turning about its own ``z``,
between the fixed frames ``base_link -> base_link_inertia`` (``rpy 0 0 pi``)
and ``wrist_3_link -> flange`` (``rpy 0 -pi/2 -pi/2``), ``flange -> tool0``
(``rpy pi/2 0 pi/2``):

    T_base_link_end(q) = Rz(pi) prod_k [Trans(x_k, y_k, z_k) R(roll_k, pitch_k, yaw_k) Rz(q_k)] F
    F = T_wrist3_flange  or  T_wrist3_flange T_flange_tool0                    (1)

vtcal's chain is ``T(q) = prod_k [pre_k origin_k Rot(a_k, q_k)] tail``
(:class:`pipeline.models.base.ChainLayout`). With ``C_k`` a rigid map whose
rotation takes ``z`` to the axis ``a_k`` and whose translation runs along
``a_k``, ``Rot(a_k, q) C_k = C_k Rz(q)``, so (1) holds exactly with

    K_1 = Rz(pi)^-1 pre_1 origin_1 C_1,   K_k = C_{k-1}^-1 pre_k origin_k C_k,
    C_6 = tail F^-1                                                             (2)

(``K_k`` the ``k``-th YAML entry), provided ``C_6`` is such a map: the flange
link's ``z`` runs along the last axis (it is ``tool0``) or its ``x`` does (it
is ``flange``). ``C_1..C_5`` are the smallest rotations taking ``z`` to
``a_k``. Any 6-revolute chain with such a flange fits; others are refused.
"""

from __future__ import annotations

import hashlib

import numpy as np

from pipeline.errors import ExportRefused
from pipeline.export.calibration import RunCalibration, header_lines
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import (
    F64,
    invert_transform,
    matrix_from_axis_angle,
    rpy_from_matrix,
    transform_from_xyz_rpy,
)
from pipeline.models.base import ChainLayout

SEGMENTS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
UR_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
T_BASE_LINK_INERTIA = transform_from_xyz_rpy([0, 0, 0], [0, 0, np.pi])
T_WRIST3_FLANGE = transform_from_xyz_rpy([0, 0, 0], [0, -np.pi / 2, -np.pi / 2])
T_FLANGE_TOOL0 = transform_from_xyz_rpy([0, 0, 0], [np.pi / 2, 0, np.pi / 2])
#: the frames vtcal's flange link may be, as ur_description names them: wrist_3 -> frame
END_FRAMES = {"tool0": T_WRIST3_FLANGE @ T_FLANGE_TOOL0, "flange": T_WRIST3_FLANGE}
_TOL = 1e-9


def z_to(axis: F64) -> F64:
    """Smallest rotation (4 x 4) taking ``z`` to the unit ``axis``."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    T = np.eye(4)
    c = np.cross([0.0, 0.0, 1.0], a)
    s = float(np.linalg.norm(c))
    if s < 1e-12:
        if a[2] < 0:
            T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # pi about x
        return T
    T[:3, :3] = matrix_from_axis_angle(c / s, float(np.arctan2(s, a[2])))
    return T


def _commutes(C: F64, axis: F64) -> bool:
    """``Rot(axis, q) C == C Rz(q)`` for all ``q``: ``C z = axis``, translation along it."""
    a = np.asarray(axis, dtype=float)
    t = C[:3, 3]
    return bool(np.linalg.norm(C[:3, 2] - a) < _TOL and np.linalg.norm(t - (t @ a) * a) < _TOL)


def ur_entries(chain: Chain) -> tuple[dict[str, tuple[F64, F64]], str]:
    """The six YAML entries ``{segment: (xyz, rpy)}`` of equation (2), and the end frame.

    Parameters
    ----------
    chain : base link to flange link of the calibrated robot

    Returns
    -------
    entries : segment name -> ((3,) m, (3,) rad roll pitch yaw)
    end : ``"tool0"`` or ``"flange"``: which ur_description frame the flange link is

    Raises
    ------
    ExportRefused
        Not six revolute joints, or a flange frame with neither ``z`` nor ``x``
        along the last axis.
    """
    L = ChainLayout.from_chain(chain)
    if L.n != 6 or L.prismatic.any():
        kinds = "prismatic joints" if L.prismatic.any() else f"{L.n} actuated joints"
        raise ExportRefused(
            f"ur-calibration: the chain {chain.base_link} -> {chain.tip_link} has {kinds}; "
            "the UR kinematics file describes 6 revolute joints"
        )
    C = [z_to(a) for a in L.axis]
    end = ""
    for name, F in END_FRAMES.items():
        C6 = L.tail @ invert_transform(F)
        if _commutes(C6, L.axis[5]):
            C[5], end = C6, name
            break
    if not end:
        raise ExportRefused(
            f"ur-calibration: the flange link {chain.tip_link!r} has neither its z (tool0) nor "
            "its x (flange) on the last joint's axis, pointing the way the joint turns "
            "positively, so ur_description's fixed wrist_3 -> flange -> tool0 frames cannot "
            "reproduce it"
        )
    entries: dict[str, tuple[F64, F64]] = {}
    left = invert_transform(T_BASE_LINK_INERTIA)
    for k, seg in enumerate(SEGMENTS):
        K = left @ L.pre[k] @ L.origin[k] @ C[k]
        entries[seg] = (K[:3, 3].copy(), rpy_from_matrix(K[:3, :3]))
        left = invert_transform(C[k])
    return entries, end


def ur_hash(entries: dict[str, tuple[F64, F64]]) -> str:
    """``calib_`` and a decimal digest of the values (the form UR's own hashes take)."""
    blob = ";".join(
        f"{seg}:" + ",".join(repr(float(v)) for v in (*xyz, *rpy))
        for seg, (xyz, rpy) in entries.items()
    )
    return "calib_" + str(int(hashlib.sha256(blob.encode()).hexdigest()[:15], 16))


def ur_yaml(cal: RunCalibration) -> str:
    """The kinematics YAML of the calibrated robot (see module docstring)."""
    entries, end = ur_entries(cal.chain)
    names = cal.chain.joint_names
    lines = ["# UR kinematics parameters written by vtcal export (format: ur-calibration)"]
    lines += [f"# {line}" for line in header_lines(cal)]
    lines += [
        f"# vtcal chain {cal.base_link} -> {cal.flange_link}: base_link and {end} of "
        "ur_description",
        "# joints in order: " + ", ".join(names),
    ]
    if tuple(names) != UR_JOINTS:
        lines.append("# NOTE: joint names differ from UR's; the order above is what matters")
    p = cal.p_flange_pin
    lines += [
        f"# virtual pin (TCP) in {cal.flange_link} ({end}), m: "
        + " ".join(repr(float(v)) for v in p),
        "# kinematics: the calibrated link geometry with the joint zero offsets folded in;",
        "# the base frame was held at nominal (touch-ups never identify it)",
        "kinematics:",
    ]
    for seg, (xyz, rpy) in entries.items():
        lines.append(f"  {seg}:")
        for key, v in zip(("x", "y", "z", "roll", "pitch", "yaw"), (*xyz, *rpy), strict=True):
            lines.append(f"    {key}: {float(v)!r}")
    lines.append(f"  hash: {ur_hash(entries)}")
    return "\n".join(lines) + "\n"
