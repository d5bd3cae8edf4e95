"""Visiting order of the chosen poses: short joint-space travel.

The cost of moving between poses ``a`` and ``b`` is the time a synchronised
joint move takes at a common speed limit, i.e. the largest joint change
``|q_a - q_b|_inf`` (rad), plus ``switch_cost`` when the move changes target
(a new target means a new image-Jacobian probe and a long approach, so the
poses of one target stay together unless splitting them saves more). The path
is open and starts at the pose nearest to ``q_start``. Nearest neighbour builds
it; 2-opt (reversing a stretch when that shortens the path; Croes 1958) then
improves it until no reversal helps.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64


def travel_costs(q: ArrayLike, target: ArrayLike, switch_cost: float) -> F64:
    """Pairwise move costs (N, N): ``max_k |q_a,k - q_b,k| + switch_cost [target differs]``."""
    q = np.asarray(q, dtype=float)
    t = np.asarray(target)
    D = np.max(np.abs(q[:, None, :] - q[None, :, :]), axis=2)
    return np.asarray(D + switch_cost * (t[:, None] != t[None, :]))


def path_length(D: F64, order: ArrayLike) -> float:
    """Summed cost of visiting ``order`` (open path)."""
    o = np.asarray(order, dtype=np.int64)
    return float(np.sum(D[o[:-1], o[1:]])) if o.size > 1 else 0.0


def order_visits(
    q: ArrayLike,
    target: ArrayLike,
    *,
    q_start: ArrayLike | None = None,
    switch_cost: float = 1.0,
    max_passes: int = 50,
) -> np.ndarray:
    """Visiting order of poses ``q`` (N, n): nearest neighbour then 2-opt.

    Parameters
    ----------
    q : (N, n) joint vectors
    target : (N,) target of each pose
    q_start : (n,) where the robot starts (default: the first pose)
    switch_cost : extra cost of a move between targets, rad
    max_passes : 2-opt passes at most

    Returns
    -------
    (N,) permutation: ``q[order]`` is the visiting sequence
    """
    q = np.asarray(q, dtype=float)
    N = len(q)
    if N <= 1:
        return np.arange(N)
    D = travel_costs(q, target, switch_cost)
    start = 0 if q_start is None else int(np.argmin(np.max(np.abs(q - q_start), axis=1)))
    order = [start]
    left = np.ones(N, dtype=bool)
    left[start] = False
    for _ in range(N - 1):
        cand = np.flatnonzero(left)
        nxt = int(cand[int(np.argmin(D[order[-1], cand]))])
        order.append(nxt)
        left[nxt] = False
    o = np.array(order)
    # 2-opt on an open path with a fixed start: reverse o[i:j+1] (1 <= i < j <= N-1)
    for _ in range(max_passes):
        improved = False
        for i in range(1, N - 1):
            a = o[i - 1]
            b = o[i]
            js = np.arange(i + 1, N)
            c = o[js]
            d_next = np.where(js + 1 < N, D[c, o[np.minimum(js + 1, N - 1)]], 0.0)
            new_next = np.where(js + 1 < N, D[b, o[np.minimum(js + 1, N - 1)]], 0.0)
            delta = D[a, c] + new_next - D[a, b] - d_next
            k = int(np.argmin(delta))
            if delta[k] < -1e-12:
                j = int(js[k])
                o[i : j + 1] = o[i : j + 1][::-1].copy()
                improved = True
        if not improved:
            break
    return o
