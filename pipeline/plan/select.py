"""Choosing N measuring poses among the candidates: random balanced starts, then exchanges.

Criteria on the reduced information ``S`` of a pose set (:mod:`pipeline.plan.design`,
eq. 2; its eigenvalues ``lambda_i = s_i^2`` are the squared singular values of the
projected, scaled identification Jacobian), all to be maximised:

* ``O1``: ``log det S`` (D-optimal; Borm & Menq 1991's O1 up to the constant ``m``);
* ``O3``: ``lambda_min`` (the minimum singular value squared; Nahvi et al. 1994);
* ``O4``: ``lambda_min / sqrt(lambda_max)`` (the noise amplification index
  ``s_min^2 / s_max``; Nahvi & Hollerbach 1996);
* ``A``: ``-trace S^-1`` (A-optimal: the summed variance of the scaled parameters).

Algorithm (DETMAX, Mitchell 1974, with excursions of one pose):

1. Start: ``n_starts`` random sets with the poses spread evenly over the targets
   (a greedy forward selection is a poor start here: a pose on a target without
   poses tells nothing, its position absorbs it, so greedy never opens a second
   target and the exchanges cannot leave that corner).
2. Exchange by ``O1`` from each start: add the candidate that raises the
   criterion most, then remove the pose of the enlarged set whose removal lowers
   it least; stop when the removed pose is the one just added (no exchange
   improves) or after ``max_exchanges``. The best run is kept; for ``O3``, ``O4``
   and ``A`` the exchange continues from it by that criterion (they are flat
   while ``S`` is rank deficient, so the D-optimal set is their start).

Additions are rated with the rank-3 update (3) of :mod:`pipeline.plan.design`:
``O1`` by the matrix determinant lemma, ``log det(I_3 + C Q)`` with ``C = (I + H)^-1``
and ``Q = At S^-1 At^T``; ``A`` by the Woodbury identity ``tr S'^-1 = tr S^-1 -
tr((C^-1 + Q)^-1 At S^-2 At^T)``; ``O3``/``O4`` exactly on a shortlist of the best
candidates by the ``A`` and ``O1`` gains. Removals are rated exactly: ``M`` is
additive over poses, so ``M - M_j`` and its Schur complement (2) are formed for
every pose ``j`` of the set at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.measurement.pin import ParamLayout
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
    start_value : criterion value of the start the kept run began from
    exchanges : accepted exchanges
    seconds : wall time
    history : criterion value after each accepted exchange
    """

    chosen: np.ndarray
    criterion: str
    value: float
    start_value: float
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


class SelectionState:
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
        t0 = ParamLayout(0, d.K).target_start(d.tk[idx])
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


def removal_values(design: Design, M: F64, chosen: np.ndarray, criterion: str) -> F64:
    """Criterion of the set without each of its poses (exact, batched)."""
    A = design.rows(chosen)
    Mj = M[None] - np.swapaxes(A, 1, 2) @ A
    return criterion_value(design.schur(Mj), criterion)


def _balanced_start(
    design: Design, n: int, allowed: np.ndarray, rng: np.random.Generator
) -> list[int]:
    """A random start set with the poses spread evenly over the targets that have candidates."""
    ks = [k for k in range(design.K) if np.any(allowed & (design.tk == k))]
    want = np.full(len(ks), n // max(len(ks), 1))
    want[: n - int(want.sum())] += 1
    chosen: list[int] = []
    for k, w in zip(ks, want, strict=True):
        pool = np.flatnonzero(allowed & (design.tk == k))
        chosen += rng.choice(pool, min(int(w), pool.size), replace=False).tolist()
    rest = np.setdiff1d(np.flatnonzero(allowed), chosen)
    if len(chosen) < n:
        chosen += rng.choice(rest, n - len(chosen), replace=False).tolist()
    return [int(c) for c in chosen]


def _exchange(
    design: Design,
    chosen: list[int],
    allowed: np.ndarray,
    criterion: str,
    max_ex: int,
    delta: float,
) -> tuple[list[int], float, int, list[float]]:
    """DETMAX exchanges of one pose from ``chosen`` until none improves ``criterion``."""
    free = allowed.copy()
    free[chosen] = False
    st = SelectionState(design, chosen, delta)
    value = float(criterion_value(design.schur(st.M), criterion))
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
        rem = removal_values(design, st.M + design.information([a]), plus, criterion)
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
        st = SelectionState(design, chosen, delta)
    return chosen, value, n_ex, history


def select_poses(
    design: Design,
    n_poses: int,
    criterion: str = "O1",
    *,
    n_starts: int = 3,
    seed: int = 0,
    max_exchanges: int | None = None,
    exclude: np.ndarray | None = None,
) -> Selection:
    """Choose ``n_poses`` candidates maximising ``criterion`` (see module docstring).

    Parameters
    ----------
    design : candidate rows (:func:`pipeline.plan.design.build_design`)
    n_poses : poses to choose (at most the number of candidates)
    criterion : ``O1``, ``O3``, ``O4`` or ``A``
    n_starts : random balanced starts of the D-optimal exchange (the best is kept)
    seed : seed of the starts
    max_exchanges : cap on accepted exchanges per run (default ``20 n_poses``)
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
    allowed = np.ones(C, dtype=bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    n_poses = int(min(n_poses, int(allowed.sum())))
    scale = float(np.mean(np.einsum("cij,cij->c", design.Ax, design.Ax))) / max(design.r, 1)
    delta = 1e-10 * max(scale, 1e-300)
    max_ex = 20 * n_poses if max_exchanges is None else max_exchanges
    rng = np.random.default_rng(seed)

    best: tuple[list[int], float, int, list[float]] | None = None
    start_value = -np.inf
    for _ in range(max(n_starts, 1)):
        start = _balanced_start(design, n_poses, allowed, rng)
        sv = float(criterion_value(design.schur(design.information(start)), criterion))
        run = _exchange(design, start, allowed, "O1", max_ex, delta)
        if best is None or run[1] > best[1]:
            best, start_value = run, sv
    assert best is not None
    chosen, value, n_ex, history = best
    if criterion != "O1":
        start_value = float(criterion_value(design.schur(design.information(chosen)), criterion))
        chosen, value, n2, history = _exchange(design, chosen, allowed, criterion, max_ex, delta)
        n_ex += n2
    final = float(criterion_value(design.schur(design.information(chosen)), criterion))
    return Selection(
        chosen=np.array(chosen, dtype=np.int64),
        criterion=criterion,
        value=final,
        start_value=start_value,
        exchanges=n_ex,
        seconds=time.perf_counter() - t0,
        history=history,
    )
