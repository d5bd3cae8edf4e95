"""Weights of a touch-up's repeated final captures when the camera had not settled.

A touch-up ends with a few captures at the same joint vector (the controller's
``repeat_captures``). Their detections are averaged. When the camera still swings
after the last move (a flange camera on a long arm), the earlier of them carry more
of the swing than the later ones: the encoders do not see it, so it is an error of
the measurement, and a plain mean carries the first capture's share of it.

The captures' own disagreement shows it. Let ``x_j`` be the centre ``(u, v)`` (or the size
``s``) of the capture ``j`` places before the last one (``j = 0``: the last). Pooled
over every touch-up and coordinate,

    D_j = mean (x_j - x_0)^2,   j >= 1.

With the same noise ``sigma^2`` in every capture and nothing else, every ``D_j`` is
``2 sigma^2``. A swing that decays makes the early ones larger. When the largest
``D_j`` exceeds the smallest by more than chance (the F-test of their ratio on the
pooled degrees of freedom, at ``alpha`` after a Bonferroni factor), each capture
gets the inverse of its variance,

    var_0 = sigma^2 = min_j D_j / 2,   var_j = max(D_j - sigma^2, sigma^2),
    w_j = 1 / var_j,

(the most settled pair taken as noise alone), and the touch-up's centre and angle
(weights from the centres) and its size (weights from the sizes, tested on their own)
are the weighted means. Otherwise there are no weights and the means are the
plain means they were (the same numbers, to the bit). Measured on the LR Mate-like
cell with vibration after moves (20 um, 50 urad, 15 Hz, decaying in 0.3 s; captures
0.21 s apart): ``sqrt(D_2)`` 0.028 px, ``sqrt(D_1)`` 0.011 px, against 0.004 / 0.004 px
on the still twin (docs/detection.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.estimation.distributions import f_sf

#: significance of the capture scatter's dependence on the capture's place
ALPHA = 1e-3


def settle_weights(
    uses: Sequence[Sequence[int]], xs: Sequence[np.ndarray], alpha: float = ALPHA
) -> np.ndarray | None:
    """Per-capture weights of the final captures (see the module docstring), or None.

    Parameters
    ----------
    uses : per touch-up, the indices of its final captures in time order
    xs : the measured quantities pooled, each (n,) over every capture: the centre
        ``(u, v)``, or the size ``(s,)`` (weighed on its own scatter: a swing moves
        the image more across than along the view, and the size loses precision
        to weights it does not need)
    alpha : significance of the largest ``D_j`` against the smallest

    Returns
    -------
    (n,) weights (1 for captures in no final block), or None: no place-dependent
    scatter found, or too few repeated captures to tell (fewer than three at the end
    of every touch-up).
    """
    return _settle(uses, xs, alpha)[0]


def settle_summary(
    uses: Sequence[Sequence[int]],
    centre: Sequence[np.ndarray],
    size: Sequence[np.ndarray],
    alpha: float = ALPHA,
) -> dict[str, dict[str, Any]]:
    """What :func:`settle_weights` found, for the report (``touchups.parquet`` metadata).

    Returns
    -------
    ``{"centre": ..., "size": ...}``, each with ``tested`` (three or more repeated
    captures), ``weighted``, ``p_value`` (the F-test, Bonferroni-corrected),
    ``scatter_px`` (``sqrt(D_j / k)`` for ``j = 1, 2, ...``: the RMS difference of
    the capture ``j`` places before the last from the last, per coordinate) and
    ``weights`` (``w_j`` for ``j = 0, 1, ...``, the last capture's first; empty when
    not weighted).
    """
    return settle(uses, centre, size, alpha)[2]


def settle(
    uses: Sequence[Sequence[int]],
    centre: Sequence[np.ndarray],
    size: Sequence[np.ndarray],
    alpha: float = ALPHA,
) -> tuple[np.ndarray | None, np.ndarray | None, dict[str, dict[str, Any]]]:
    """The centre's and the size's :func:`settle_weights` and their :func:`settle_summary`,
    each pooled scatter computed once."""
    wc, info_c = _settle(uses, centre, alpha)
    ws, info_s = _settle(uses, size, alpha)
    return wc, ws, {"centre": info_c, "size": info_s}


def _settle(
    uses: Sequence[Sequence[int]], xs: Sequence[np.ndarray], alpha: float
) -> tuple[np.ndarray | None, dict[str, Any]]:
    """(:func:`settle_weights`' result, :func:`settle_summary`'s entry) of ``xs``."""
    info: dict[str, Any] = {"tested": False, "weighted": False, "p_value": float("nan")}
    info.update(scatter_px=[], weights=[])
    depth = max((len(x) for x in uses), default=0)
    if depth < 3:
        return None, info
    sums, dof = np.zeros(depth), np.zeros(depth)
    for use in uses:
        last = use[-1] if len(use) else -1
        for j in range(1, len(use)):
            i = use[-1 - j]
            sums[j] += sum((x[i] - x[last]) ** 2 for x in xs)
            dof[j] += len(xs)
    places = np.flatnonzero(dof[1:] >= 2) + 1
    if places.size < 2:
        return None, info
    D = sums[places] / dof[places]
    lo, hi = int(np.argmin(D)), int(np.argmax(D))
    if not D[lo] > 0 or not np.all(np.isfinite(D)):
        return None, info
    p = f_sf(float(D[hi] / D[lo]), float(dof[places[hi]]), float(dof[places[lo]]))
    p = min(1.0, p * places.size * (places.size - 1))
    info.update(tested=True, p_value=float(p), scatter_px=[float(x) for x in np.sqrt(D)])
    if p >= alpha:
        return None, info
    sigma2 = float(D[lo]) / 2.0
    var = np.full(depth, sigma2)
    var[places] = np.maximum(D - sigma2, sigma2)
    w = np.ones(len(xs[0]))
    for use in uses:
        for j, i in enumerate(reversed(use)):
            w[i] = sigma2 / var[j]
    info.update(weighted=True, weights=[float(x) for x in sigma2 / var])
    return w, info


def wmean(x: np.ndarray, idx: Sequence[int], w: np.ndarray | None) -> float:
    """Mean of ``x[idx]``, weighted by ``w[idx]`` when there are weights."""
    if w is None:
        return float(np.mean(x[list(idx)]))
    return float(np.average(x[list(idx)], weights=w[list(idx)]))
