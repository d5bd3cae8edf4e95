"""Did the robot change between two calibrations? One test over every parameter at once.

Two recordings ``a`` (earlier) and ``b`` give estimates ``z_a, z_b`` of the
quantities both identified (kinematic corrections and the pin,
:mod:`pipeline.audit.fit`) with covariances ``C_a, C_b``. The recordings are
independent, so under "nothing changed" the difference is zero-mean with::

    delta = z_b - z_a,        C = C_a + C_b                                   (C1)

``C`` may be singular (directions the two sets of poses identify only
together); its eigen-decomposition ``C = U diag(lam) U^T`` keeps the ``r``
eigenvalues above ``RANK_TOL * max(lam)`` (the identifiable subspace), and the
difference, whitened and projected on it::

    w = diag(lam_r)^(-1/2) U_r^T delta,     T = |w|^2 ~ chi2(r)               (C2)

Each covariance carries its fit's variance factor ``sigma^2 = |r|^2 / f``, estimated
on ``f`` residual degrees of freedom (about 12 on a 3 x 6 touch-up recording with
the full model), so ``T`` is not chi-square but, as in the global congruency test of
geodetic deformation analysis, ``T / r ~ F(r, f)`` with the Welch-Satterthwaite
degrees of freedom of the two variance factors' shares ``t_a = tr(W C_a W^T)``,
``t_b = tr(W C_b W^T)`` (``t_a + t_b = r``)::

    f = (t_a + t_b)^2 / (t_a^2 / f_a + t_b^2 / f_b),    p = P(F(r, f) > T / r)   (C3)

(``f -> inf`` gives back ``chi2(r)``; without the fits' degrees of freedom it is
used). At ``r = 30``, ``f = 24`` the 1 % point of ``T`` is 77 where ``chi2(30)``'s is
51: the chi-square read the variance factors' own scatter as change (seeded, 12
residual dof per fit, 3000 pairs: 9 % false alarms at ``alpha = 1 %`` with it, 0.57 %
with (C3); ``tests/test_audit.py``).

A change is declared when ``p < alpha``: one test, so the nominal
false-alarm rate per comparison is ``alpha`` whatever the number of parameters
(the per-parameter 3-sigma flags of ``vtcal compare`` make about
``0.0027 * n`` false alarms per comparison, more where the estimates are
correlated). The null is not exact: on fresh simulated histories without events
(``benchmarks/bench_audit.py --cases none --first-seed N``) ``T / r`` runs
about 4 % above ``F(r, f)`` over its whole range, and the measured rate is
1.6 % at ``alpha = 1 %``, 0.3 % at 0.1 % (2650 comparisons). The default
``alpha = 0.001`` keeps the measured rate under 1 % per comparison (about 1.5 %
per history of six) with the events the audit is for still far beyond it (the
weakest 0.1 mm link origin of the image-level histories at ``p = 1e-14``).

``z`` holds the fitted target centres too: the base frame against the targets
is never identified, so a moved base shows only there, as a rigid motion of
every centre (read as such by :mod:`pipeline.audit.attribute`). Targets are
compared by label; a target one recording did not touch is left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2
from scipy.stats import f as f_dist

from pipeline.audit.fit import Estimate
from pipeline.kinematics.se3 import F64

#: eigenvalues of C below this fraction of the largest are outside the identifiable subspace
RANK_TOL = 1e-9
#: false-alarm rate per comparison
ALPHA = 0.001


@dataclass
class Difference:
    """(C1)-(C2) for two estimates.

    Attributes
    ----------
    names : the E quantities both estimated ; delta : (E,) ; cov : (E, E) ``C_a + C_b``
    W : (r, E) the whitening projection ``diag(lam_r)^(-1/2) U_r^T`` ; w : (r,) ``W delta``
    T : ``|w|^2`` ; dof : r ; p : (C3) (``P(chi2(r) > T)`` when ``f_dof`` is infinite)
    f_dof : (C3)'s ``f``, the variance factors' degrees of freedom (inf: known)
    """

    names: list[str]
    delta: F64
    cov: F64
    W: F64
    w: F64
    T: float
    dof: int
    p: float
    f_dof: float = math.inf

    def changed(self, alpha: float = ALPHA) -> bool:
        return self.p < alpha

    def z_scores(self) -> F64:
        """Per quantity ``delta / sqrt(C_ii)`` (for tables, not for the decision)."""
        s = np.sqrt(np.clip(np.diag(self.cov), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.asarray(np.where(s > 0, self.delta / s, np.nan))


def whiten(cov: F64, rank_tol: float = RANK_TOL) -> F64:
    """(C2)'s projection ``W`` (r, E) of a covariance: ``W C W^T = I_r``."""
    lam, U = np.linalg.eigh(0.5 * (cov + cov.T))
    keep = lam > rank_tol * max(float(lam.max()), 0.0) if len(lam) else np.zeros(0, bool)
    return np.asarray((U[:, keep] / np.sqrt(lam[keep])).T)


def sf(T: float, r: int, f: float) -> float:
    """``P(chi2(r) > T)`` for a known variance factor (``f`` infinite), else ``P(F(r, f) > T / r)``."""
    if r <= 0:
        return 1.0
    return float(chi2.sf(T, r)) if not math.isfinite(f) else float(f_dist.sf(T / r, r, f))


def isf(alpha: float, r: int, f: float) -> float:
    """The ``T`` that :func:`sf` gives ``alpha``: ``chi2_isf(alpha, r)`` or ``r F_isf(alpha, r, f)``."""
    if r <= 0:
        return 0.0
    return float(chi2.isf(alpha, r)) if not math.isfinite(f) else r * float(f_dist.isf(alpha, r, f))


def satterthwaite(W: F64, C_a: F64, C_b: F64, f_a: float, f_b: float) -> float:
    """(C3)'s ``f`` from the two covariances' shares of the whitened space; inf when either
    fit's degrees of freedom are unknown (0 or less)."""
    if not (f_a > 0 and f_b > 0):
        return math.inf
    t_a = float(np.trace(W @ C_a @ W.T))
    t_b = float(np.trace(W @ C_b @ W.T))
    den = t_a * t_a / f_a + t_b * t_b / f_b
    return (t_a + t_b) ** 2 / den if den > 0 else math.inf


def difference_test(
    z_a: F64,
    C_a: F64,
    z_b: F64,
    C_b: F64,
    names: list[str],
    f_a: float = 0.0,
    f_b: float = 0.0,
) -> Difference:
    """(C1)-(C3) on aligned vectors ``z_a, z_b`` (E,) with covariances (E, E) and the
    residual degrees of freedom ``f_a, f_b`` of the fits that made them (0: unknown)."""
    delta = np.asarray(z_b, dtype=float) - np.asarray(z_a, dtype=float)
    Ca, Cb = np.asarray(C_a, dtype=float), np.asarray(C_b, dtype=float)
    C = Ca + Cb
    W = whiten(C)
    w = W @ delta
    T = float(w @ w)
    r = int(W.shape[0])
    f = satterthwaite(W, Ca, Cb, f_a, f_b) if r else math.inf
    return Difference(list(names), delta, C, W, w, T, r, sf(T, r, f), f)


def compare_estimates(a: Estimate, b: Estimate) -> Difference:
    """(C1)-(C2) over the quantities both recordings estimated (b's order)."""
    ia = a.index()
    names = [n for n in b.names if n in ia]
    jb = [b.index()[n] for n in names]
    ja = [ia[n] for n in names]
    return difference_test(
        a.z[ja], a.cov[np.ix_(ja, ja)], b.z[jb], b.cov[np.ix_(jb, jb)], names, a.dof, b.dof
    )
