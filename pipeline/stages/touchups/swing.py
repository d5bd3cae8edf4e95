"""A touch-up's final centre freed of the camera's swing after the last move (one mode).

When :mod:`pipeline.stages.touchups.settle` finds that the camera had not settled
at the repeated final captures, weighting them still leaves the swing that is in
the last one. An arm that stops rings mostly in one mode: the camera's offset
decays as ``e^(-t/tau) sin(2 pi f t + phi)`` along one direction, and the
target's image moves with it. At a touch-up's final captures ``k = 0, 1, 2``
(the last three, equally spaced by ``dt``) the centre ``x_k = (u_k, v_k)`` is
then

    x_k = c + a r^k sin(phi + k Delta),      r = e^(-dt/tau),  Delta = 2 pi f dt   (S1)

with ``c`` the centre of the still camera (what the touch-up measures), ``a``
(2,) the swing's amplitude and direction in the image and ``phi`` its phase at
the first of the three: five unknowns per touch-up for its six numbers. ``r``
and ``Delta`` are the arm's and shared by every touch-up. Sampled every ``dt``,
only ``Delta`` modulo ``2 pi`` and up to its sign is seen, so it is searched in
``(0, pi)``.

Fit. The shared ``(r, Delta)`` is hard to tell from the least-squares cost of
(S1): it is nearly flat over them (``benchmarks/bench_settle_model.py``). The
captures' pooled second moments tell it (:func:`moment_globals`, (S2)): with the
phase uniform over touch-ups, the mean squared differences of the three pairs of
captures are three equations for the swing's mean square amplitude, ``r`` and
``Delta``, given the noise (from the least-squares residual of (S1) at the best
pair of a grid, :data:`R_GRID` x :data:`DELTA_GRID`, which also starts the
solve). Then each touch-up's ``phi`` is searched on :data:`PHI_GRID` (a sign of
``a`` covers the other half turn) with ``c, a`` the linear least-squares
solution of (S1), and its ``c`` replaces the weighted mean centre. The size and
the long-axis angle keep their settle-weighted means (a swing moves the image
across the view, not its size).

Measured on the LR Mate-like cell with vibration after moves (15 Hz, decaying in
0.3 s, captures 0.21 s apart: ``r`` 0.50, ``Delta`` 54 deg), seeds 7-14, shipped
model against the truth (mean shape RMS; still twin 0.0106 mm): settle weights
alone 0.0183 mm; (S1) at the grid's best pair 0.0138; at the truth's pair 0.0120;
at (S2)'s 0.0118 (``bench_optics.py``; docs/detection.md has the figures). On synthetic
captures (``tests/test_touchup_swing.py``) the centre's error is 0.44-0.62x the
settle-weighted mean's. A still camera has no swing to find: the fit would only
add noise (about 0.003 px on these cells), which is why it is used only when the
settle test has found the camera swinging.

Used only when (i) the settle test found the centres' scatter depends on the
capture's place and (ii) at least :data:`MIN_TOUCHUPS` touch-ups end in three or
more found captures whose last three are equally spaced (each spacing within
:data:`SPACING_TOL` of the median); a touch-up that is not keeps its weighted
centre. Otherwise nothing changes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: decay per capture searched (``r`` of (S1))
R_GRID = np.linspace(0.2, 0.9, 15)
#: phase step per capture searched (``Delta`` of (S1), rad)
DELTA_GRID = np.radians(np.arange(10.0, 171.0, 10.0))
#: each touch-up's phase at its first final capture, searched (rad)
PHI_GRID = np.linspace(0.0, np.pi, 90, endpoint=False)
#: fewer touch-ups with three final captures than this: the shared ``(r, Delta)`` is not fitted
MIN_TOUCHUPS = 10
#: the last three captures' spacings must agree with their median to this share
SPACING_TOL = 0.1


@dataclass(frozen=True)
class Swing:
    """What :func:`remove_swing` fitted.

    Attributes
    ----------
    centres : {touch-up index: (u, v)} the still camera's centres ``c`` (px)
    r, delta : the shared decay per capture and phase step (rad) of (S1)
    spacing_s : the captures' spacing ``dt`` (s)
    swing_last_px : RMS over the touch-ups of the swing (S1) puts into the last capture
    shift_px : RMS of ``c`` minus the last capture's centre
    """

    centres: dict[int, tuple[float, float]]
    r: float
    delta: float
    spacing_s: float
    swing_last_px: float
    shift_px: float

    def summary(self) -> dict[str, float | int]:
        """For ``touchups.parquet``'s settle metadata (the report shows it)."""
        return {
            "n": len(self.centres),
            "r": self.r,
            "delta_deg": float(np.degrees(self.delta)),
            "spacing_s": self.spacing_s,
            "swing_last_px": self.swing_last_px,
            "shift_px": self.shift_px,
        }


def fit_one_mode(
    X: np.ndarray, r: float, delta: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S1) fitted to every touch-up at one ``(r, Delta)``.

    Parameters
    ----------
    X : (n, 3, 2) centres of each touch-up's last three captures, in time order (px)
    r, delta : decay per capture and phase step (rad)

    Returns
    -------
    cost : (n,) each touch-up's least squared residual over the phase grid (px²)
    c : (n, 2) the still camera's centre
    swing_last : (n, 2) the fitted swing at the last capture, ``a r^2 sin(phi + 2 Delta)``
    """
    k = np.arange(3)
    G = (r**k)[None, :] * np.sin(PHI_GRID[:, None] + k[None, :] * delta)  # (P, 3)
    A = np.stack([np.ones_like(G), G], axis=2)  # (P, 3, 2): columns c and a
    solve = np.linalg.pinv(np.einsum("pki,pkj->pij", A, A))  # a phase with G = 0 is singular
    beta = np.einsum("pij,pkj,nkc->npic", solve, A, X)  # (n, P, 2, coord)
    fitted = np.einsum("pki,npic->npkc", A, beta)
    res = ((X[:, None] - fitted) ** 2).sum(axis=(2, 3))  # (n, P)
    best = res.argmin(axis=1)
    n = np.arange(len(X))
    return res[n, best], beta[n, best, 0, :], beta[n, best, 1, :] * G[best, 2][:, None]


def moment_globals(
    X: np.ndarray, sigma2: float, start: tuple[float, float]
) -> tuple[float, float] | None:
    """``(r, Delta)`` of (S2) from the captures' pooled differences, or None.

    With the phase uniform over touch-ups, ``E[sin(phi + i D) sin(phi + j D)] =
    cos((j - i) D) / 2``, so per coordinate

        E (x_i - x_j)^2 = A^2 / 2 (r^2i + r^2j - 2 r^(i+j) cos((j - i) Delta)) + 2 sigma^2   (S2)

    for the pairs ``(0, 1), (0, 2), (1, 2)``: three equations for ``A^2, r,
    Delta`` given the noise ``sigma^2`` (from the fit's residual). Solved by
    bounded least squares on the relative misfit from ``start``; None when it does
    not converge or the amplitude vanishes.
    """
    from scipy.optimize import least_squares

    pairs = ((0, 1), (0, 2), (1, 2))
    obs = np.array([np.mean((X[:, i] - X[:, j]) ** 2) for i, j in pairs])

    def misfit(p: np.ndarray) -> np.ndarray:
        a2, r, d = p
        pred = [
            a2 / 2 * (r ** (2 * i) + r ** (2 * j) - 2 * r ** (i + j) * np.cos((j - i) * d))
            + 2 * sigma2
            for i, j in pairs
        ]
        return (np.array(pred) - obs) / obs

    x0 = np.array([max(2.0 * obs[1], 1e-12), *start])
    lo, hi = [0.0, 0.05, 0.01], [np.inf, 0.99, np.pi - 0.01]
    sol = least_squares(misfit, np.clip(x0, lo, hi), bounds=(lo, hi))
    if not sol.success or not sol.x[0] > 0:
        return None
    return float(sol.x[1]), float(sol.x[2])


def remove_swing(
    uses: Sequence[Sequence[int]], t_s: np.ndarray, u: np.ndarray, v: np.ndarray
) -> Swing | None:
    """The still camera's centre of every touch-up by (S1), or None where not used.

    Parameters
    ----------
    uses : per touch-up, its final captures' indices in time order
    t_s : (N,) capture times (s); u, v : (N,) detected centres (px)

    Returns
    -------
    :class:`Swing`, or None: fewer than :data:`MIN_TOUCHUPS` touch-ups whose last
    three final captures are found and equally spaced (each spacing within
    :data:`SPACING_TOL` of the median over all of them); the others keep their
    settle-weighted centres (no entry in ``centres``). Whether the camera swings at
    all is the caller's test (``touchup_settle``).
    """
    ks = [k for k, use in enumerate(uses) if len(use) >= 3]
    if len(ks) < MIN_TOUCHUPS:
        return None
    last3 = np.array([list(uses[k])[-3:] for k in ks])
    gaps = np.diff(t_s[last3], axis=1)
    dt = float(np.median(gaps))
    X = np.stack([u[last3], v[last3]], axis=2)  # (n, 3, 2)
    ok = np.all(np.abs(gaps - dt) <= SPACING_TOL * dt, axis=1) & np.all(np.isfinite(X), axis=(1, 2))
    if not dt > 0 or int(ok.sum()) < MIN_TOUCHUPS:
        return None
    ks = [k for k, keep in zip(ks, ok, strict=True) if keep]
    X = X[ok]
    cost = np.array([[fit_one_mode(X, r, d)[0].sum() for r in R_GRID] for d in DELTA_GRID])
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    r, delta = float(R_GRID[j]), float(DELTA_GRID[i])
    sigma2 = float(cost[i, j]) / len(X)  # 6 numbers - 5 unknowns: 1 residual dof per touch-up
    found = moment_globals(X, sigma2, (r, delta))
    if found is not None:
        r, delta = found
    _, c, swing = fit_one_mode(X, r, delta)
    return Swing(
        centres={k: (float(c[n, 0]), float(c[n, 1])) for n, k in enumerate(ks)},
        r=r,
        delta=delta,
        spacing_s=dt,
        swing_last_px=float(np.sqrt(np.mean(np.sum(swing**2, axis=1)))),
        shift_px=float(np.sqrt(np.mean(np.sum((c - X[:, 2]) ** 2, axis=1)))),
    )
