"""Modified Denavit-Hartenberg table of the calibrated robot, Hayati's beta on parallel axes.

Convention (Craig 1986, "modified DH"), written in the file's header: frame
``i`` sits on joint ``i``'s axis (``z_i`` along the axis, positive rotation =
positive joint value), and

    T_base_flange(q) = T_base_0 prod_{i=1..n} L_i(q_i) T_n_flange
    L_i(q) = Rx(alpha_i) Ry(beta_i) Tx(a_i) Rz(theta_i + q_i) Tz(d_i)          (1)

``T_base_0`` is frame 1 at ``q = 0`` (so row 1 is all zeros) and ``T_n_flange``
the flange in frame ``n``; both are given as xyz / rpy (``R = Rz(y) Ry(p)
Rx(r)``). ``theta_i`` is the joint's zero offset in this table's frames.

Frames from the calibrated axis lines at ``q = 0`` (``z_i``, a point ``p_i``):

* axes ``i`` and ``i+1`` not parallel (standard DH): ``x_i`` along their common
  normal, frame ``i``'s origin its foot on axis ``i`` (``x_i = z_i x z_{i+1}``
  when they intersect); then ``beta_{i+1} = 0``;
* nearly parallel (angle below ``MDHModel.parallel_tol`` = 0.01 rad), where
  the common normal is ill-defined and ``d`` jumps by metres for a microradian
  of tilt: Hayati & Mirmirani (1985) add ``beta_{i+1}``, a rotation about
  ``y``. The origin of frame ``i`` is where the previous link lands on axis
  ``i`` (``d_i = 0``); ``Q``, the point where axis ``i+1`` crosses the plane
  through that origin perpendicular to ``z_{i+1}``, is reached along
  ``u = (Q - o_i) / a_{i+1}``; ``x_i`` is the unit vector perpendicular to
  ``z_i`` and to ``z_{i+1} x u``, signed so that ``Rx(alpha) Ry(beta)`` maps
  ``x_i`` to ``u``. Then (1) is exact for every link.

Every link is checked by rebuilding it from its five numbers; a residual
above ``1e-9`` (m or rad) refuses the export with one line, as do prismatic
joints (no DH form here).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import ExportRefused
from pipeline.export.calibration import RunCalibration, header_lines
from pipeline.kinematics.chain import Chain, fk, fk_frames
from pipeline.kinematics.se3 import F64, invert_transform, matrix_from_axis_angle, rpy_from_matrix
from pipeline.models.mdh import MDHModel

COLUMNS = ("alpha", "beta", "a", "theta", "d")
_EX, _EY, _EZ = np.eye(3)
_TOL = 1e-9


def _rot(axis: F64, t: float) -> F64:
    T = np.eye(4)
    T[:3, :3] = matrix_from_axis_angle(axis, t)
    return T


def _trans(axis: F64, s: float) -> F64:
    T = np.eye(4)
    T[:3, 3] = axis * s
    return T


def link_transform(alpha: float, beta: float, a: float, theta: float, d: float) -> F64:
    """``L = Rx(alpha) Ry(beta) Tx(a) Rz(theta) Tz(d)`` (equation (1) at ``q = 0``)."""
    return _rot(_EX, alpha) @ _rot(_EY, beta) @ _trans(_EX, a) @ _rot(_EZ, theta) @ _trans(_EZ, d)


def _unit(v: F64) -> F64 | None:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else None


def _perp(v: F64, z: F64) -> F64 | None:
    return _unit(v - z * (v @ z))


def _common_normal(zi: F64, pi: F64, zj: F64, pj: F64) -> tuple[F64, F64]:
    """Feet on axis i and axis j of the common normal of two non-parallel lines."""
    b = zi @ zj
    w0 = pi - pj
    den = 1.0 - b * b
    ti = (b * (zj @ w0) - zi @ w0) / den
    tj = ((zj @ w0) - b * (zi @ w0)) / den
    return pi + ti * zi, pj + tj * zj


def _alpha_beta(zz: F64) -> tuple[float, float]:
    """``alpha, beta`` with ``Rx(alpha) Ry(beta) z = zz`` (``zz`` in the previous frame)."""
    beta = float(np.arcsin(np.clip(zz[0], -1.0, 1.0)))
    alpha = float(np.arctan2(-zz[1], zz[2]))
    return alpha, beta


def mdh_frames(chain: Chain) -> tuple[F64, np.ndarray]:
    """MDH frames ``(n, 4, 4)`` in the base frame at ``q = 0`` and the Hayati flags ``(n,)``.

    ``hayati[i]`` is True when link ``i`` (from frame ``i-1`` to ``i``) uses ``beta``.
    """
    _, G = fk_frames(chain, np.zeros(chain.n_dof))
    G = G[0]
    axes = np.array([j.axis for j in chain.actuated], dtype=float)
    z = np.einsum("nij,nj->ni", G[:, :3, :3], axes)
    p = G[:, :3, 3].copy()
    n = len(z)
    hayati = np.zeros(n, dtype=bool)
    for i in range(1, n):
        hayati[i] = np.linalg.norm(np.cross(z[i - 1], z[i])) < np.sin(MDHModel.parallel_tol)
    F = np.zeros((n, 4, 4))
    # where the previous link lands on axis 0: the base origin's foot on it
    land = p[0] + z[0] * ((-p[0]) @ z[0])
    prev_x: F64 | None = None
    for i in range(n):
        zi = z[i]
        x: F64 | None = None
        o = land
        if i + 1 < n and not hayati[i + 1]:
            o, foot_j = _common_normal(zi, p[i], z[i + 1], p[i + 1])
            x = _perp(foot_j - o, zi)
            if x is None:  # intersecting axes
                x = _unit(np.cross(zi, z[i + 1]))
            land = foot_j
        elif i + 1 < n:  # Hayati link i+1
            zj = z[i + 1]
            Q = p[i + 1] + zj * ((o - p[i + 1]) @ zj)
            u = _unit(Q - o)
            if u is not None:
                x = _unit(np.cross(zi, np.cross(zj, u)))
                if x is not None:
                    y = np.cross(zi, x)
                    alpha, beta = _alpha_beta(np.array([zj @ x, zj @ y, zj @ zi]))
                    Rf = np.column_stack([x, y, zi]) @ (_rot(_EX, alpha) @ _rot(_EY, beta))[:3, :3]
                    if Rf[:, 0] @ u < 0:
                        x = -x
            land = Q
        if x is None:
            x = _perp(prev_x, zi) if prev_x is not None else None
        if x is None:
            x = _perp(_EX if abs(zi[0]) < 0.9 else _EY, zi)
        assert x is not None
        F[i, :3, 0], F[i, :3, 1], F[i, :3, 2], F[i, :3, 3] = x, np.cross(zi, x), zi, o
        F[i, 3, 3] = 1.0
        prev_x = x
    return F, hayati


def mdh_table(chain: Chain) -> tuple[F64, F64, F64, np.ndarray]:
    """The table of equation (1).

    Returns
    -------
    rows : (n, 5) ``alpha, beta, a, theta, d`` (rad, rad, m, rad, m)
    T_base_0 : (4, 4)
    T_n_flange : (4, 4)
    hayati : (n,) bool, rows that use ``beta``

    Raises
    ------
    ExportRefused
        A prismatic joint, or a link the five numbers do not rebuild to ``1e-9``.
    """
    for j in chain.actuated:
        if j.type == "prismatic":
            raise ExportRefused(
                f"dh: joint {j.name!r} is prismatic; the DH export is revolute only"
            )
    F, hayati = mdh_frames(chain)
    n = len(F)
    rows = np.zeros((n, 5))
    for i in range(1, n):
        rel = invert_transform(F[i - 1]) @ F[i]
        alpha, beta = _alpha_beta(rel[:3, 2])
        if not hayati[i]:
            beta = 0.0
        Rxy = (_rot(_EX, alpha) @ _rot(_EY, beta))[:3, :3]
        Rz = Rxy.T @ rel[:3, :3]
        theta = float(np.arctan2(Rz[1, 0], Rz[0, 0]))
        t = Rxy.T @ rel[:3, 3]
        rows[i] = (alpha, beta, t[0], theta, t[2])
        err = np.abs(link_transform(*rows[i]) - rel).max()
        if not err < _TOL:
            name = chain.joint_names[i]
            raise ExportRefused(
                f"dh: link to joint {name!r} is not representable as (alpha, beta, a, theta, d): "
                f"residual {err:.3g} after the construction (axes {i} and {i + 1})"
            )
    T_n_flange = invert_transform(F[-1]) @ fk(chain, np.zeros(n))
    return rows, F[0], T_n_flange, hayati


def _xyz_rpy(T: F64) -> str:
    vals = (*T[:3, 3], *rpy_from_matrix(T[:3, :3]))
    return " ".join(f"{float(v)!r}" for v in vals)


def dh_text(cal: RunCalibration) -> str:
    """The table as text: ``#`` header with the convention, then one row per joint."""
    rows, T0, Tf, hayati = mdh_table(cal.chain)
    lines = ["# modified DH table (Craig) with Hayati's beta, written by vtcal export (format: dh)"]
    lines += [f"# {line}" for line in header_lines(cal)]
    lines += [
        "# convention: T_base_flange(q) = BASE * prod_i [Rx(alpha_i) Ry(beta_i) Tx(a_i)",
        "#   Rz(theta_i + q_i) Tz(d_i)] * TOOL; frame i on joint i's axis (z along the URDF",
        "#   axis, positive = positive joint value); beta_i != 0 only where axes i-1 and i are",
        "#   (nearly) parallel (Hayati), else 0. BASE and TOOL: x y z (m) roll pitch yaw (rad),",
        "#   R = Rz(yaw) Ry(pitch) Rx(roll). Units: metres, radians. Joint values q as in",
        f"#   joint_states (the URDF's convention). Chain: {cal.base_link} -> {cal.flange_link};",
        "#   the virtual pin (TCP) is not in TOOL; it is p_flange_pin below.",
        "# p_flange_pin (m): " + " ".join(f"{float(v)!r}" for v in cal.p_flange_pin),
        f"BASE {_xyz_rpy(T0)}",
        f"TOOL {_xyz_rpy(Tf)}",
        "# joint alpha beta a theta d hayati",
    ]
    for name, r, h in zip(cal.chain.joint_names, rows, hayati, strict=True):
        lines.append(f"{name} " + " ".join(f"{float(v)!r}" for v in r) + f" {int(h)}")
    return "\n".join(lines) + "\n"
