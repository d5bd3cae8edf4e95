"""Choosing N measuring poses among the candidates: greedy start, then exchanges.

Criteria on the reduced information ``S`` of a pose set (:mod:`pipeline.plan.design`,
eq. 2; its eigenvalues ``lambda_i = s_i^2`` are the squared singular values of the
projected, scaled identification Jacobian), all to be maximised:

* ``O1``: ``log det S`` (D-optimal; Borm & Menq 1991's O1 up to the constant ``m``);
* ``O3``: ``lambda_min`` (the minimum singular value squared; Nahvi et al. 1994);
* ``O4``: ``lambda_min / sqrt(lambda_max)`` (the noise amplification index
  ``s_min^2 / s_max``; Nahvi & Hollerbach 1996);
* ``A``: ``-trace S^-1`` (A-optimal: the summed variance of the scaled parameters).

Algorithm (DETMAX, Mitchell 1974, with excursions of one pose):

1. Greedy forward selection by ``O1`` with a tiny ridge ``delta I`` on ``S`` (the
   D-optimal gain of a candidate is ``log det(I_3 + C Q)`` with ``C = (I + H)^-1``,
   ``Q = At S^-1 At^T`` from the rank-3 update (3) of the design module, the
   matrix determinant lemma); the greedy set is the start for every criterion
   (E- and noise-amplification criteria are flat until ``S`` has full rank).
2. Exchange: add the candidate that raises the criterion most, then remove the
   pose of the enlarged set whose removal lowers it least; stop when the removed
   pose is the one just added (no exchange improves) or after ``max_exchanges``.
   Additions are rated with the rank-3 update: ``O1`` by the determinant lemma,
   ``A`` by the Woodbury identity ``tr S'^-1 = tr S^-1 - tr((C^-1 + Q)^-1 At S^-2 At^T)``,
   ``O3``/``O4`` exactly on a shortlist of the best candidates by the ``A`` and ``O1``
   gains. Removals are rated exactly: ``M`` is additive over poses, so ``M - M_j``
   and its Schur complement (2) are formed for every pose ``j`` of the set at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.plan.design import NUISANCE_RIDGE, Design

CRITERIA = ("O1", "O3", "O4", "A")
SHORTLIST = 48


@dataclass
class Selection:
    """The chosen poses and how the search went.

    Attributes
    ----------
    chosen : (N,) candidate indices (into the design), in selection order
    criterion : criterion name
    value : criterion value of the final set (see module docstring)
    greedy_value : criterion value after the greedy start
    exchanges : accepted exchanges
    seconds : wall time
    history : criterion value after each accepted exchange
    """

    chosen: np.ndarray
    criterion: str
    value: float
    greedy_value: float
    exchanges: int
    seconds: float
    history: list[float] = field(default_factory=list)


def criterion_value(S: F64, criterion: str) -> F64:
    """The criterion of one ``(r, r)`` or a batch ``(B, r, r)`` of reduced informations."""
    lam = np.linalg.eigvalsh(S)
    lmin = lam[..., 0]
    if criterion == "O1":
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(np.where(lmin > 0, np.sum(np.log(np.abs(lam)), axis=-1), -np.inf))
    if criterion == "O3":
        return np.asarray(lmin)
    if criterion == "O4":
        return np.asarray(lmin / np.sqrt(np.maximum(lam[..., -1], 1e-300)))
    if criterion == "A":
        with np.errstate(divide="ignore"):
            return np.asarray(np.where(lmin > 0, -np.sum(1.0 / np.abs(lam), axis=-1), -np.inf))
    raise ValueError(f"unknown criterion {criterion!r} (known: {', '.join(CRITERIA)})")


class _State:
    """Information of the current set and the quantities the rank-3 update needs."""

    def __init__(self, design: Design, chosen: list[int], delta: float) -> None:
        self.d = design
        self.delta = delta
        r = design.r
        M = design.information(chosen) if chosen else np.zeros((design.p, design.p))
        self.M = M
        Mnn = M[r:, r:] + NUISANCE_RIDGE * np.eye(design.p - r)
        self.Pn = np.linalg.inv(Mnn)
        self.G = self.Pn @ M[r:, :r]
        S = M[:r, :r] - M[:r, r:] @ self.G
        self.S = 0.5 * (S + S.T) + delta * np.eye(r)
        self.Sinv = np.linalg.inv(self.S)

    def update_terms(self, idx: np.ndarray) -> tuple[F64, F64]:
        """``At`` (B, 3, r) and ``C = (I + H)^-1`` (B, 3, 3) of candidates ``idx`` (eq. 3)."""
        d = self.d
        R = d.R[idx]
        t0 = 3 + 3 * d.tk[idx]
        ar3 = np.arange(3)
        tr = t0[:, None] + ar3  # (B, 3) target rows/cols in nuisance space
        Gt = self.G[tr]  # (B, 3, r)
        At = d.Ax[idx] - (R @ self.G[:3]) + Gt
        Ppp = self.Pn[:3, :3]
        Ppt = self.Pn[:3][:, tr].transpose(1, 0, 2)  # (B, 3, 3): pin rows, target cols
        Ptt = self.Pn[tr[:, :, None], tr[:, None, :]]  # (B, 3, 3)
        RPpt = R @ Ppt
        H = R @ Ppp @ np.swapaxes(R, 1, 2) - RPpt - np.swapaxes(RPpt, 1, 2) + Ptt
        C = np.linalg.inv(np.eye(3) + H)
        return At, C

    def add_gains(self, idx: np.ndarray, criterion: str) -> F64:
        """Change of the criterion if each candidate of ``idx`` were added (O1, A exact)."""
        At, C = self.update_terms(idx)
        SiAt = self.Sinv @ np.swapaxes(At, 1, 2)  # (B, r, 3)
        Q = At @ SiAt
        if criterion == "O1":
            sign, ld = np.linalg.slogdet(np.eye(3) + C @ Q)
            return np.asarray(np.where(sign > 0, ld, -np.inf))
        if criterion == "A":
            Cinv = np.linalg.inv(C)
            num = np.swapaxes(SiAt, 1, 2) @ SiAt  # At S^-2 At^T
            return np.asarray(np.trace(np.linalg.solve(Cinv + Q, num), axis1=1, axis2=2))
        raise ValueError(criterion)

    def added_values(self, idx: np.ndarray, criterion: str) -> F64:
        """Exact criterion of ``S + At^T C At`` for each candidate of ``idx``."""
        At, C = self.update_terms(idx)
        S1 = self.S + np.swapaxes(At, 1, 2) @ C @ At
        return criterion_value(S1, criterion)


def _removal_values(design: Design, M: F64, chosen: np.ndarray, criterion: str) -> F64:
    """Criterion of the set without each of its poses (exact, batched)."""
    A = design.rows(chosen)
    Mj = M[None] - np.swapaxes(A, 1, 2) @ A
    return criterion_value(design.schur(Mj), criterion)


def select_poses(
    design: Design,
    n_poses: int,
    criterion: str = "O1",
    *,
    max_exchanges: int | None = None,
    exclude: np.ndarray | None = None,
) -> Selection:
    """Choose ``n_poses`` candidates maximising ``criterion`` (see module docstring).

    Parameters
    ----------
    design : candidate rows (:func:`pipeline.plan.design.build_design`)
    n_poses : poses to choose (at most the number of candidates)
    criterion : ``O1``, ``O3``, ``O4`` or ``A``
    max_exchanges : cap on accepted exchanges (default ``10 n_poses``)
    exclude : optional boolean mask of candidates never to choose

    Returns
    -------
    Selection
    """
    import time

    if criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r} (known: {', '.join(CRITERIA)})")
    t0 = time.perf_counter()
    C = len(design)
    n_poses = int(min(n_poses, C))
    allowed = np.ones(C, dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    scale = float(np.mean(np.einsum("cij,cij->c", design.Ax, design.Ax))) / max(design.r, 1)
    delta = 1e-8 * max(scale, 1e-300)

    # 1. greedy D-optimal start
    chosen: list[int] = []
    free = allowed.copy()
    st = _State(design, chosen, delta)
    for _ in range(n_poses):
        idx = np.flatnonzero(free)
        g = st.add_gains(idx, "O1")
        best = int(idx[int(np.argmax(g))])
        chosen.append(best)
        free[best] = False
        st = _State(design, chosen, delta)
    greedy_value = float(criterion_value(design.schur(st.M), criterion))

    # 2. exchanges
    max_ex = 10 * n_poses if max_exchanges is None else max_exchanges
    value = greedy_value
    history: list[float] = []
    n_ex = 0
    while n_ex < max_ex:
        idx = np.flatnonzero(free)
        if idx.size == 0:
            break
        if criterion in ("O1", "A"):
            a = int(idx[int(np.argmax(st.add_gains(idx, criterion)))])
        else:
            gA = st.add_gains(idx, "A")
            gD = st.add_gains(idx, "O1")
            k = min(SHORTLIST, idx.size)
            short = np.unique(
                np.concatenate([idx[np.argsort(-gA)[:k]], idx[np.argsort(-gD)[: k // 2]]])
            )
            a = int(short[int(np.argmax(st.added_values(short, criterion)))])
        plus = np.array(chosen + [a], dtype=np.int64)
        M_plus = st.M + design.information([a])
        rem = _removal_values(design, M_plus, plus, criterion)
        j = int(np.argmax(rem))
        if plus[j] == a or not rem[j] > value + 1e-12 * max(abs(value), 1.0):
            break
        removed = int(plus[j])
        chosen = [int(c) for c in plus if c != removed]
        free[a] = False
        free[removed] = True
        value = float(rem[j])
        history.append(value)
        n_ex += 1
        st = _State(design, chosen, delta)
    final = float(criterion_value(design.schur(st.M), criterion))
    return Selection(
        chosen=np.array(chosen, dtype=np.int64),
        criterion=criterion,
        value=final,
        greedy_value=greedy_value,
        exchanges=n_ex,
        seconds=time.perf_counter() - t0,
        history=history,
    )
