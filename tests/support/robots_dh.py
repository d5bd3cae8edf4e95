"""Standard-DH test arms and an independent closed-form DH forward kinematics.

Used only by tests: the URDF built from a DH table is read by vtcal's own URDF
reader, and the same table is evaluated here with the textbook DH matrix
``A_i = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` written out element by element.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

# (a, alpha, d, theta_offset) per joint, metres / radians.
UR5E_DH = [
    (0.0, np.pi / 2, 0.1625, 0.0),
    (-0.425, 0.0, 0.0, 0.0),
    (-0.3922, 0.0, 0.0, 0.0),
    (0.0, np.pi / 2, 0.1333, 0.0),
    (0.0, -np.pi / 2, 0.0997, 0.0),
    (0.0, 0.0, 0.0996, 0.0),
]

# FANUC LR Mate 200iD-like: J2 parallel to J3, offset wrist (a3), spherical wrist.
LRMATE_DH = [
    (0.050, -np.pi / 2, 0.330, 0.0),
    (0.330, 0.0, 0.0, -np.pi / 2),
    (0.035, -np.pi / 2, 0.0, 0.0),
    (0.0, np.pi / 2, -0.335, 0.0),
    (0.0, -np.pi / 2, 0.0, 0.0),
    (0.0, 0.0, -0.080, 0.0),
]

# A 7-axis arm (iiwa-like, zero link offsets in a and alternating twists).
IIWA_DH = [
    (0.0, -np.pi / 2, 0.340, 0.0),
    (0.0, np.pi / 2, 0.0, 0.0),
    (0.0, np.pi / 2, 0.400, 0.0),
    (0.0, -np.pi / 2, 0.0, 0.0),
    (0.0, -np.pi / 2, 0.400, 0.0),
    (0.0, np.pi / 2, 0.0, 0.0),
    (0.0, 0.0, 0.126, 0.0),
]


def dh_matrix(a: float, alpha: float, d: float, theta: np.ndarray) -> np.ndarray:
    """Textbook standard-DH link transform for a batch of ``theta``: ``(N,) -> (N, 4, 4)``."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    A = np.zeros(theta.shape + (4, 4))
    A[..., 0, 0] = ct
    A[..., 0, 1] = -st * ca
    A[..., 0, 2] = st * sa
    A[..., 0, 3] = a * ct
    A[..., 1, 0] = st
    A[..., 1, 1] = ct * ca
    A[..., 1, 2] = -ct * sa
    A[..., 1, 3] = a * st
    A[..., 2, 1] = sa
    A[..., 2, 2] = ca
    A[..., 2, 3] = d
    A[..., 3, 3] = 1.0
    return A


def dh_fk(table: list[tuple[float, float, float, float]], q: np.ndarray) -> np.ndarray:
    """Closed-form DH forward kinematics ``prod_i A_i(q_i + offset_i)``: ``(N, n) -> (N, 4, 4)``."""
    T = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4))
    for i, (a, alpha, d, off) in enumerate(table):
        T = T @ dh_matrix(a, alpha, d, q[:, i] + off)
    return T


def dh_urdf(table: list[tuple[float, float, float, float]], name: str = "dh_arm") -> str:
    """A URDF whose base_link -> flange chain equals the DH table.

    Joint ``i`` rotates about its frame's z. The origin of joint ``i + 1`` in
    link ``i`` is ``Tz(d_i) Tx(a_i) Rx(alpha_i)``, i.e. ``xyz = (a_i, 0, d_i)``,
    ``R = Rx(alpha_i)``; a joint's theta offset is appended to its own origin as
    ``Rz(offset)`` (it commutes with the motion about z). The origin rotation is
    turned into URDF rpy (extrinsic x-y-z) with scipy, not with vtcal. The last
    link's DH transform becomes the fixed flange joint.
    """

    def rpy(alpha: float, off: float) -> str:
        R = Rotation.from_euler("x", alpha).as_matrix() @ Rotation.from_euler("z", off).as_matrix()
        with warnings.catch_warnings():  # gimbal lock is harmless: any valid rpy will do
            warnings.simplefilter("ignore", UserWarning)
            angles = Rotation.from_matrix(R).as_euler("xyz")
        return " ".join(repr(float(x)) for x in angles)

    n = len(table)
    links = "".join(f'<link name="link_{i}"/>' for i in range(1, n + 1))
    parts = [f'<?xml version="1.0"?>\n<robot name="{name}">', '<link name="base_link"/>', links]
    parts.append(
        '<link name="flange"><visual><geometry><box size="0.01 0.01 0.01"/></geometry>'
        "</visual></link>"
    )
    prev_xyz, prev_alpha = (0.0, 0.0, 0.0), 0.0
    parent = "base_link"
    for i, (a, alpha, d, off) in enumerate(table, start=1):
        xyz = " ".join(repr(float(x)) for x in prev_xyz)
        parts.append(
            f'<joint name="joint_{i}" type="revolute"><parent link="{parent}"/>'
            f'<child link="link_{i}"/><origin xyz="{xyz}" rpy="{rpy(prev_alpha, off)}"/>'
            '<axis xyz="0 0 1"/>'
            '<limit lower="-6.2832" upper="6.2832" effort="1" velocity="1"/></joint>'
        )
        prev_xyz, prev_alpha = (a, 0.0, d), float(alpha)
        parent = f"link_{i}"
    xyz = " ".join(repr(float(x)) for x in prev_xyz)
    parts.append(
        f'<joint name="flange_joint" type="fixed"><parent link="{parent}"/><child link="flange"/>'
        f'<origin xyz="{xyz}" rpy="{rpy(prev_alpha, 0.0)}"/></joint>'
    )
    parts.append("</robot>")
    return "\n".join(parts)
