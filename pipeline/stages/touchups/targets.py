"""Touch-up extraction, step 4: which touch-ups share a target.

The virtual-pin point ``p`` (flange frame) is unknown, but all touch-ups of one
target satisfy ``R_i p + t_i = c``: :func:`group_targets` finds the ``p`` that
makes most touch-ups coincide in pairs (RANSAC), refines it, and groups the
points ``c_i = R_i p + t_i``. The steps are described in
:mod:`pipeline.stages.touchups.stage`.
"""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.se3 import rotation_angle


def group_targets(
    Ts: np.ndarray, *, radius_m: float, ransac_samples: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Label touch-ups by target from their final flange poses (``touchup`` step 4).

    RANSAC over triples of two pairs of touch-ups (distinct orientations) each
    assumed to share a target solves ``(R_i - R_j) p = t_j - t_i``,
    ``(R_k - R_m) p = t_m - t_k``; the ``p`` that makes most touch-ups coincide in
    pairs wins, is refined with the groups (``R_i p + t_i = c_g`` for every
    member), and the points ``c_i = R_i p + t_i`` are grouped within ``radius_m``.

    Parameters
    ----------
    Ts : (n, 4, 4) final flange poses of the touch-ups (nominal model)
    radius_m : grouping radius (``TouchupConfig.group_radius_m``)
    ransac_samples : random hypotheses when the pairs of pairs are more
        (``TouchupConfig.ransac_samples``)
    seed : of the random hypotheses (``TouchupConfig.seed``)

    Returns
    -------
    labels : (n,) 0, 1, ... in first-touch order
    p : (3,) the pin estimate (flange frame)
    """
    n = len(Ts)
    if n == 1:
        return np.zeros(1, dtype=np.int64), np.zeros(3)
    R = Ts[:, :3, :3]
    t = Ts[:, :3, 3]
    ang = rotation_angle(np.einsum("iba,jbc->ijac", R, R))  # angle of R_i^T R_j
    rng = np.random.default_rng(seed)
    eps = radius_m * 0.25

    best_p = np.zeros(3)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if ang[i, j] > 0.05]
    # hypotheses: two pairs assumed to share a target each (6 equations, 3 unknowns);
    # every combination of pairs of consecutive touch-ups first (runs usually touch
    # one target several times in a row), then random combinations of any pairs
    adjacent = [pq for pq in pairs if pq[1] == pq[0] + 1]
    hyps: list[tuple[tuple[int, int], tuple[int, int]]] = [
        (adjacent[x], adjacent[y])
        for x in range(len(adjacent))
        for y in range(x + 1, len(adjacent))
    ][: 4 * ransac_samples]
    if len(pairs) > 1:
        n_pp = len(pairs) * (len(pairs) - 1) // 2
        if n_pp <= ransac_samples:
            hyps += [
                (pairs[x], pairs[y]) for x in range(len(pairs)) for y in range(x + 1, len(pairs))
            ]
        else:
            for _ in range(ransac_samples):
                x, y = rng.choice(len(pairs), size=2, replace=False)
                hyps.append((pairs[int(x)], pairs[int(y)]))
    elif pairs:
        hyps.append((pairs[0], pairs[0]))
    if hyps:
        best_p = _best_hypothesis(R, t, np.asarray(hyps, dtype=np.int64), ang > 0.05, eps)
    labels = _cluster(R @ best_p + t, radius_m)
    # refine p with the groups: R_i p + t_i = c_g for every member
    for _ in range(2):
        rows, rhs = [], []
        for g in np.unique(labels):
            idx = np.nonzero(labels == g)[0]
            if len(idx) < 2:
                continue
            Rm = R[idx].mean(axis=0)
            tm = t[idx].mean(axis=0)
            for ii in idx:
                rows.append(R[ii] - Rm)
                rhs.append(tm - t[ii])
        if not rows:
            break
        p_new, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
        if not np.all(np.isfinite(p_new)):
            break
        best_p = p_new
        labels = _cluster(R @ best_p + t, radius_m)
    return labels, best_p


def _best_hypothesis(
    R: np.ndarray, t: np.ndarray, hyps: np.ndarray, distinct: np.ndarray, eps: float
) -> np.ndarray:
    """The RANSAC winner among the hypotheses ``hyps`` ``(H, 2, 2)`` (two index pairs each).

    Each hypothesis solves ``[R_i - R_j; R_k - R_m] p = [t_j - t_i; t_m - t_k]`` in the
    least-squares (minimum-norm) sense; its score is the number of touch-ups that
    coincide (``|c_a - c_b| < eps``, ``c = R p + t``) with another of distinct
    orientation (``distinct`` (n, n)), ties broken by the smaller ``sum min(|c_a - c_b|,
    eps)``; the first best wins. All hypotheses are solved and scored as arrays, in
    blocks of about 1e5 distances (from each block's Gram matrices).

    Returns
    -------
    p : (3,) the winning pin hypothesis (flange frame)
    """
    i, j, k, m = hyps[:, 0, 0], hyps[:, 0, 1], hyps[:, 1, 0], hyps[:, 1, 1]
    A = np.concatenate([R[i] - R[j], R[k] - R[m]], axis=1)  # (H, 6, 3)
    b = np.concatenate([t[j] - t[i], t[m] - t[k]], axis=1)  # (H, 6)
    # minimum-norm least squares with lstsq's default cut-off (eps * max(M, N))
    P = np.einsum("hab,hb->ha", np.linalg.pinv(A, rcond=np.finfo(float).eps * 6), b)
    n = len(t)
    block = max(1, 100_000 // max(1, n * n))  # a block's distances stay in cache
    counts = np.empty(len(P), dtype=np.int64)
    sums = np.empty(len(P))
    eps2 = eps * eps
    for s0 in range(0, len(P), block):
        c = np.einsum("nab,hb->hna", R, P[s0 : s0 + block]) + t[None]  # (h, n, 3)
        c -= c.mean(axis=1, keepdims=True)
        sq = np.einsum("hna,hna->hn", c, c)
        # |c_a - c_b|^2 from the Gram matrix (rounding ~1e-8 m on ~1 m points)
        d2 = c @ c.transpose(0, 2, 1)
        d2 *= -2.0
        d2 += sq[:, :, None]
        d2 += sq[:, None, :]
        near = d2 < eps2
        counts[s0 : s0 + block] = (near & distinct[None]).any(axis=2).sum(axis=1)
        # sum of min(d, eps): eps for every far pair, the distance for every near one
        np.maximum(d2, 0.0, out=d2)
        np.sqrt(d2, out=d2, where=near)
        d2[~near] = eps
        sums[s0 : s0 + block] = d2.reshape(len(d2), -1).sum(axis=1)
    top = np.flatnonzero(counts == counts.max())
    return np.asarray(P[top[int(np.argmin(sums[top]))]])


def _cluster(c: np.ndarray, radius: float) -> np.ndarray:
    """Greedy grouping in order: join the nearest existing group centre within ``radius``."""
    labels = np.full(len(c), -1, dtype=np.int64)
    centres: list[list[np.ndarray]] = []
    for i, ci in enumerate(c):
        if centres:
            d = [np.linalg.norm(ci - np.mean(g, axis=0)) for g in centres]
            k = int(np.argmin(d))
            if d[k] < radius:
                labels[i] = k
                centres[k].append(ci)
                continue
        labels[i] = len(centres)
        centres.append([ci])
    return labels
