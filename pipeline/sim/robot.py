"""The simulated robot: seeded kinematic deviations, true URDFs, nominal inverse kinematics.

Deviation convention (the same as the ground-truth files): for every actuated
joint with URDF origin ``T_o = Trans(xyz) RPY(rpy)`` and axis ``a``,

    T_o' = Trans(xyz + dxyz) @ RPY(rpy) @ RPY(drpy) @ Rot(a, dq0)

so ``dxyz`` moves the joint (link length / offset errors), ``drpy`` tilts it
(link twist errors, non-parallel "parallel" axes) and ``dq0`` is the joint
zero offset (the encoder reads ``q`` while the joint sits at ``q + dq0``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from pipeline.kinematics.chain import Chain, fk, jacobian
from pipeline.kinematics.se3 import (
    F64,
    matrix_from_axis_angle,
    matrix_from_rpy,
    rpy_from_matrix,
    transform_from,
)

DEVIATION_NOTE = "origin' = origin(xyz+dxyz) @ RPY(drpy) @ Rot(axis, dq0)"


def draw_deviations(
    chain: Chain,
    rng: np.random.Generator,
    sigma_xyz_m: float = 5e-4,
    sigma_rpy_rad: float = 1.5e-3,
    sigma_q0_rad: float = 1e-3,
) -> dict[str, dict[str, Any]]:
    """Draw per-joint deviations (normal, clipped at 2.5 sigma) for every actuated joint.

    Returns
    -------
    dict joint name -> {"dxyz_m": [3], "drpy_rad": [3], "dq0_rad": float, "note": str}
    """
    out: dict[str, dict[str, Any]] = {}
    for j in chain.actuated:
        dxyz = np.clip(rng.normal(0.0, sigma_xyz_m, 3), -2.5 * sigma_xyz_m, 2.5 * sigma_xyz_m)
        drpy = np.clip(rng.normal(0.0, sigma_rpy_rad, 3), -2.5 * sigma_rpy_rad, 2.5 * sigma_rpy_rad)
        dq0 = float(np.clip(rng.normal(0.0, sigma_q0_rad), -2.5 * sigma_q0_rad, 2.5 * sigma_q0_rad))
        out[j.name] = {
            "dxyz_m": [float(x) for x in dxyz],
            "drpy_rad": [float(x) for x in drpy],
            "dq0_rad": dq0,
            "note": DEVIATION_NOTE,
        }
    return out


def deviated_origins(chain: Chain, deviations: dict[str, dict[str, Any]]) -> dict[str, F64]:
    """``T_parent_joint`` of every deviated joint, per :data:`DEVIATION_NOTE`."""
    origins: dict[str, F64] = {}
    for j in chain.actuated:
        if j.name not in deviations:
            continue
        d = deviations[j.name]
        T = j.T_parent_joint.copy()
        T[:3, 3] += np.asarray(d["dxyz_m"], dtype=float)
        R = (
            T[:3, :3]
            @ matrix_from_rpy(d["drpy_rad"])
            @ matrix_from_axis_angle(j.axis, d["dq0_rad"])
        )
        origins[j.name] = transform_from(R, T[:3, 3])
    return origins


def _fmt(x: float) -> str:
    return repr(float(x))


def urdf_with_origins(xml: str, origins: dict[str, F64], name_suffix: str = "") -> str:
    """Rewrite the ``<origin>`` of the named joints of a URDF (everything else kept)."""
    root = ET.fromstring(xml)
    if name_suffix:
        root.set("name", root.get("name", "robot") + name_suffix)
    for el in root.findall("joint"):
        name = el.get("name")
        if name not in origins:
            continue
        T = origins[str(name)]
        origin = el.find("origin")
        if origin is None:
            origin = ET.SubElement(el, "origin")
        rpy = rpy_from_matrix(T[:3, :3])
        origin.set("xyz", " ".join(_fmt(v) for v in T[:3, 3]))
        origin.set("rpy", " ".join(_fmt(v) for v in rpy))
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def urdf_with_pin(xml: str, flange_link: str, p_flange_pin: ArrayLike) -> str:
    """Add link ``virtual_pin`` on fixed joint ``virtual_pin_joint`` at ``p_flange_pin``."""
    root = ET.fromstring(xml)
    ET.SubElement(root, "link", {"name": "virtual_pin"})
    j = ET.SubElement(root, "joint", {"name": "virtual_pin_joint", "type": "fixed"})
    ET.SubElement(j, "parent", {"link": flange_link})
    ET.SubElement(j, "child", {"link": "virtual_pin"})
    p = np.asarray(p_flange_pin, dtype=float)
    ET.SubElement(j, "origin", {"xyz": " ".join(_fmt(v) for v in p), "rpy": "0 0 0"})
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def pose_error(T_goal: F64, T: F64) -> F64:
    """6-vector ``[p_goal - p; rotvec(R_goal R^T)]`` (base frame)."""
    e = np.empty(6)
    e[:3] = T_goal[:3, 3] - T[:3, 3]
    e[3:] = Rotation.from_matrix(T_goal[:3, :3] @ T[:3, :3].T).as_rotvec()
    return e


def solve_ik(
    chain: Chain,
    T_goal: F64,
    q_init: ArrayLike,
    *,
    q_rest: ArrayLike | None = None,
    max_iter: int = 200,
    tol: float = 1e-11,
    damping: float = 1e-4,
    respect_limits: bool = True,
) -> tuple[F64, bool]:
    """Damped least-squares IK ``fk(chain, q) = T_goal`` from ``q_init``.

    ``dq = J^T (J J^T + lambda^2 I)^{-1} e`` with the geometric Jacobian of
    :func:`pipeline.kinematics.jacobian` and ``e`` from :func:`pose_error`;
    steps are limited to 0.3 rad. For redundant chains ``q_rest`` adds a
    null-space pull ``(I - J^+ J) k (q_rest - q)`` during the first iterations.
    With ``respect_limits`` the iterate is clipped to the joint limits.

    Returns
    -------
    q : (n,)
    ok : bool
        Converged (``|e| < tol`` per component scale) within limits.
    """
    q = np.array(q_init, dtype=float)
    lo, hi = chain.lower, chain.upper
    n = q.size
    rest = None if q_rest is None else np.asarray(q_rest, dtype=float)
    ok = False
    for it in range(max_iter):
        T = fk(chain, q)
        e = pose_error(T_goal, T)
        err = float(np.max(np.abs(e)))
        if err < tol:
            ok = True
            break
        if it == 60 and err > 1e-4:
            break  # not converging (out of reach or stuck on a limit): let the caller re-seed
        J = jacobian(chain, q)
        JJt = J @ J.T + (damping**2) * np.eye(6)
        dq = J.T @ np.linalg.solve(JJt, e)
        if rest is not None and n > 6 and it < 20:
            Jp = J.T @ np.linalg.inv(J @ J.T + 1e-9 * np.eye(6))
            dq += (np.eye(n) - Jp @ J) @ (0.3 * (rest - q))
        m = np.max(np.abs(dq))
        if m > 0.3:
            dq *= 0.3 / m
        q = q + dq
        if respect_limits:
            q = np.clip(q, lo, hi)
    if ok and respect_limits:
        ok = bool(np.all(q >= lo - 1e-12) and np.all(q <= hi + 1e-12))
    return q, ok
