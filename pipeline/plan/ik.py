"""Batched nominal inverse kinematics for many candidate flange poses at once.

The same damped-least-squares iteration as the simulator's single-pose
:func:`pipeline.sim.robot.solve_ik` (Wampler 1986; Nakamura & Hanafusa 1986),

    dq = J^T (J J^T + lambda^2 I)^-1 e,   e = [p_goal - p; rotvec(R_goal R^T)]

with the geometric Jacobian of :func:`pipeline.kinematics.chain.jacobian`,
steps limited to 0.3 rad and the iterate clipped to the joint limits, run on
a whole batch of goals (one row each) so that thousands of candidates cost a
few hundred vectorised forward-kinematics calls instead of a Python loop per
pose. Rows stop as they converge; a row still far off after 60 iterations is
given up (out of reach or blocked by a limit) so the caller can re-seed it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain, fk, jacobian
from pipeline.kinematics.se3 import F64


def rotation_log(R: F64) -> F64:
    """Rotation vectors of a batch of rotation matrices, (N, 3, 3) -> (N, 3).

    ``theta = atan2(|v|, (tr R - 1) / 2)`` with ``v = vee(R - R^T) / 2``; near
    ``theta = pi`` the axis comes from the largest column of ``(R + I) / 2``.
    """
    v = 0.5 * np.stack(
        [R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1
    )
    s = np.linalg.norm(v, axis=1)
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    th = np.arctan2(s, c)
    out = np.zeros_like(v)
    small = s < 1e-9
    ok = ~small
    out[ok] = v[ok] * (th[ok] / s[ok])[:, None]
    near_pi = small & (c < 0)
    for i in np.flatnonzero(near_pi):
        B = 0.5 * (R[i] + np.eye(3))
        k = int(np.argmax(np.diag(B)))
        a = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        out[i] = np.pi * a
    return out


def solve_ik_batch(
    chain: Chain,
    T_goal: ArrayLike,
    q_seed: ArrayLike,
    *,
    max_iter: int = 120,
    tol: float = 1e-10,
    damping: float = 1e-3,
    give_up_at: int = 60,
) -> tuple[F64, np.ndarray]:
    """Joint vectors with ``fk(chain, q_i) = T_goal_i``, solved for all rows together.

    Parameters
    ----------
    chain : nominal chain, base link to flange
    T_goal : (N, 4, 4) flange goals, base frame
    q_seed : (N, n) start joint vectors (clipped into the limits)
    max_iter, tol : iteration budget; convergence when every component of the
        pose error is below ``tol`` (m, rad)
    damping : ``lambda`` of the damped least squares
    give_up_at : iteration after which rows with error above 1e-4 stop

    Returns
    -------
    q : (N, n)
    ok : (N,) bool, converged (the iterate always stays inside the limits)
    """
    T_goal = np.asarray(T_goal, dtype=float)
    lo, hi = chain.lower, chain.upper
    q = np.clip(np.array(q_seed, dtype=float), lo, hi)
    N = len(q)
    ok = np.zeros(N, dtype=bool)
    active = np.ones(N, dtype=bool)
    lam2 = damping**2
    for it in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        qa = q[idx]
        T = fk(chain, qa)
        Tg = T_goal[idx]
        e = np.empty((idx.size, 6))
        e[:, :3] = Tg[:, :3, 3] - T[:, :3, 3]
        e[:, 3:] = rotation_log(Tg[:, :3, :3] @ np.transpose(T[:, :3, :3], (0, 2, 1)))
        err = np.max(np.abs(e), axis=1)
        done = err < tol
        ok[idx[done]] = True
        stop = done | ((err > 1e-4) if it >= give_up_at else np.zeros_like(done))
        active[idx[stop]] = False
        keep = ~stop
        if not keep.any():
            break
        idx, qa, e = idx[keep], qa[keep], e[keep]
        J = jacobian(chain, qa)
        JJt = J @ np.transpose(J, (0, 2, 1)) + lam2 * np.eye(6)
        dq = np.einsum("nji,nj->ni", J, np.linalg.solve(JJt, e[:, :, None])[:, :, 0])
        m = np.max(np.abs(dq), axis=1)
        dq *= np.minimum(1.0, 0.3 / np.maximum(m, 1e-300))[:, None]
        q[idx] = np.clip(qa + dq, lo, hi)
    return q, ok
