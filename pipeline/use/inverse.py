"""Compensation: the joint vectors that put the calibrated robot's flange (or pin) on targets.

For each target, from a starting joint vector ``q0`` (the nominal program's
joints, usually: the solution stays on the same branch), Gauss-Newton on the
calibrated forward map (:meth:`pipeline.use.calibration.Calibration.pin_and_rotation`)::

    r(q) = [ t(q) - t*,  L log(R*^T R(q)) ]     (flange pose: 6 rows)            (I1)
    r(q) = p_pin(q) - p*                         (pin position: 3 rows)
    dq   = -J^T (J J^T + mu I)^-1 r,   J = dr/dq by central differences           (I2)

``mu`` is ``DAMPING`` times the mean diagonal of ``J J^T``, raised a
thousandfold on a row whose step failed and lowered tenfold after one that
worked (Levenberg-Marquardt; Nocedal & Wright, *Numerical Optimization*, 2nd
ed., section 10.3): near a wrist singularity the undamped step is huge.

``L`` = 1 m/rad weighs orientation against position; (I2) is the damped
minimum-norm step, so a redundant arm (7 joints for 6 or 3 rows) moves as
little as it can from ``q0``. A step is kept only when it lowers ``|r|``
(else halved). The residual is evaluated exactly each iteration, so the
difference Jacobian changes the rate, not the fixed point: converged rows
reach ``|r|`` of 1e-12 m (``TOL_M``) where the target is reachable.

Every row runs at once (one forward call per iteration for all rows and
their ``2 n`` differences).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64

#: converged when the position residual is below this (m) and the angle below TOL_M rad
TOL_M = 1e-12
#: weight of orientation against position in (I1), m/rad
LENGTH_M = 1.0
#: central-difference step of (I2), rad (m for a prismatic joint)
STEP = 1e-6
MAX_ITER = 100
#: the damping mu of (I2), relative to the mean diagonal of J J^T (keeps a singular arm solvable)
DAMPING = 1e-12
#: a row whose damping grew past this is as close as it gets (a target out of reach)
MAX_DAMPING = 1e6


@dataclass(frozen=True)
class Solution:
    """Compensated joint vectors and how well they reach their targets.

    Attributes
    ----------
    q : (N, n) joint vectors
    residual_m : (N,) position left between the reached point and its target, m
    residual_rad : (N,) orientation left (flange targets; NaN for pin targets), rad
    converged : (N,) bool: ``residual_m <= 1e-9 m`` (and the angle below 1e-9 rad)
    inside : (N,) bool: inside the joint ranges the calibration covered
    outside : (N,) joints outside them ('' inside)
    within_limits : (N,) bool: inside the URDF's joint limits
    """

    q: F64
    residual_m: F64
    residual_rad: F64
    converged: np.ndarray
    inside: np.ndarray
    outside: list[str]
    within_limits: np.ndarray


def _residual(cal: Any, q: F64, target: F64, point: str, payload_kg: float | None) -> F64:
    """(I1) per row, (N, 6) or (N, 3)."""
    if point == "pin":
        p, _ = cal.pin_and_rotation(q, payload_kg)
        out: F64 = p - target[:, :3, 3]
        return out
    p, R = cal.pin_and_rotation(q, payload_kg, point=np.zeros(3))
    Rt = np.transpose(target[:, :3, :3], (0, 2, 1))
    w = Rotation.from_matrix(Rt @ R).as_rotvec()
    return np.concatenate([p - target[:, :3, 3], LENGTH_M * w], axis=1)


def _line_search(
    cal: Any,
    q: F64,
    r: F64,
    cost: F64,
    idx: np.ndarray,
    dq: F64,
    T: F64,
    point: str,
    payload_kg: float | None,
) -> np.ndarray:
    """Take ``alpha dq`` (alpha = 1, 1/2, ...) on rows ``idx`` where it lowers ``|r|``.

    Updates ``q``, ``r``, ``cost`` in place; returns, per row of ``idx``, whether
    no step length lowered it.
    """
    alpha = 1.0
    todo = np.ones(len(idx), dtype=bool)
    for _ in range(40):
        k = np.flatnonzero(todo)
        rows = idx[k]
        qn = q[rows] + alpha * dq[k]
        rn = _residual(cal, qn, T[rows], point, payload_kg)
        cn = np.einsum("ni,ni->n", rn, rn)
        better = cn < cost[rows]
        q[rows[better]], r[rows[better]], cost[rows[better]] = qn[better], rn[better], cn[better]
        todo[k[better]] = False
        if not todo.any():
            break
        alpha *= 0.5
    return todo


def solve(
    cal: Any,
    T_base_target: ArrayLike,
    q0: ArrayLike,
    point: str = "flange",
    payload_kg: float | None = None,
) -> Solution:
    """(I1)-(I2) for every target; see the module docstring.

    Parameters
    ----------
    cal : :class:`pipeline.use.calibration.Calibration`
    T_base_target : (N, 4, 4) (or (4, 4)) targets in the base frame
    q0 : (N, n) or (n,) starting joints
    point : ``"flange"`` (pose) or ``"pin"`` (position of the virtual pin)
    payload_kg : payload at the flange (None: as in training)
    """
    if point not in ("flange", "pin"):
        raise BadInput(f"compensate: point must be 'flange' or 'pin', not {point!r}")
    T = np.asarray(T_base_target, dtype=float)
    T = T[None] if T.ndim == 2 else T
    N = len(T)
    q = cal.as_joints(q0)
    q = np.repeat(q, N, axis=0) if len(q) == 1 and N > 1 else q.copy()
    if len(q) != N:
        raise BadInput(f"compensate: {N} targets but {len(q)} starting joint vectors")
    n = q.shape[1]
    r = _residual(cal, q, T, point, payload_kg)
    cost = np.einsum("ni,ni->n", r, r)
    damp = np.full(N, DAMPING)  # per row: raised where a step failed (Levenberg-Marquardt)
    for _ in range(MAX_ITER):
        active = cost > TOL_M**2
        if not active.any():
            break
        idx = np.flatnonzero(active)
        qa, Ta = q[idx], T[idx]
        steps = np.concatenate(
            [qa + STEP * e for e in np.eye(n)] + [qa - STEP * e for e in np.eye(n)]
        )
        rr = _residual(cal, steps, np.tile(Ta, (2 * n, 1, 1)), point, payload_kg)
        rr = rr.reshape(2 * n, len(idx), -1)
        J = np.transpose((rr[:n] - rr[n:]) / (2 * STEP), (1, 2, 0))  # (A, rows, n)
        JJt = J @ np.transpose(J, (0, 2, 1))
        mu = damp[idx] * (np.trace(JJt, axis1=1, axis2=2) / JJt.shape[1] + 1e-30)
        JJt = JJt + mu[:, None, None] * np.eye(J.shape[1])
        dq = -np.einsum(
            "aij,aj->ai",
            np.transpose(J, (0, 2, 1)),
            np.linalg.solve(JJt, r[idx][..., None])[..., 0],
        )
        stalled = _line_search(cal, q, r, cost, idx, dq, T, point, payload_kg)
        damp[idx] = np.where(stalled, damp[idx] * 1e3, np.maximum(damp[idx] * 0.1, DAMPING))
        if (damp[idx] > MAX_DAMPING).all():  # no row can lower its residual: as close as it gets
            break
    res_m = np.linalg.norm(r[:, :3], axis=1)
    res_rad = (
        np.linalg.norm(r[:, 3:], axis=1) / LENGTH_M if point == "flange" else np.full(N, np.nan)
    )
    conv = (res_m <= 1e-9) & ((res_rad <= 1e-9) | np.isnan(res_rad))
    inside, outside = cal.covers(q)
    within = np.all((q >= cal.limit_lower - 1e-12) & (q <= cal.limit_upper + 1e-12), axis=1)
    return Solution(q, res_m, res_rad, conv, inside, outside, within)
