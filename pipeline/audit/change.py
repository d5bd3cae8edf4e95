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

A change is declared when ``P(chi2(r) > T) < alpha``: one test, so the
false-alarm rate per comparison is ``alpha`` whatever the number of parameters
(the per-parameter 3-sigma flags of ``vtcal compare`` make about
``0.0027 * n`` false alarms per comparison, more where the estimates are
correlated). Over a history of ``n`` recordings (``n - 1`` comparisons) the
chance of at least one false alarm is ``1 - (1 - alpha)^(n - 1)``; the default
``alpha = 0.01`` gives 4.9 % over six recordings. The rate measured on
simulated histories without events is printed by ``benchmarks/bench_audit.py``.

``z`` holds the fitted target centres too: the base frame against the targets
is never identified, so a moved base shows only there, as a rigid motion of
every centre (read as such by :mod:`pipeline.audit.attribute`). Targets are
compared by label; a target one recording did not touch is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from pipeline.audit.fit import Estimate
from pipeline.kinematics.se3 import F64

#: eigenvalues of C below this fraction of the largest are outside the identifiable subspace
RANK_TOL = 1e-9
#: false-alarm rate per comparison
ALPHA = 0.01


@dataclass
class Difference:
    """(C1)-(C2) for two estimates.

    Attributes
    ----------
    names : the E quantities both estimated ; delta : (E,) ; cov : (E, E) ``C_a + C_b``
    W : (r, E) the whitening projection ``diag(lam_r)^(-1/2) U_r^T`` ; w : (r,) ``W delta``
    T : ``|w|^2`` ; dof : r ; p : ``P(chi2(r) > T)``
    """

    names: list[str]
    delta: F64
    cov: F64
    W: F64
    w: F64
    T: float
    dof: int
    p: float

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


def difference_test(z_a: F64, C_a: F64, z_b: F64, C_b: F64, names: list[str]) -> Difference:
    """(C1)-(C2) on aligned vectors ``z_a, z_b`` (E,) with covariances (E, E)."""
    delta = np.asarray(z_b, dtype=float) - np.asarray(z_a, dtype=float)
    C = np.asarray(C_a, dtype=float) + np.asarray(C_b, dtype=float)
    W = whiten(C)
    w = W @ delta
    T = float(w @ w)
    r = int(W.shape[0])
    p = float(chi2.sf(T, r)) if r else 1.0
    return Difference(list(names), delta, C, W, w, T, r, p)


def compare_estimates(a: Estimate, b: Estimate) -> Difference:
    """(C1)-(C2) over the quantities both recordings estimated (b's order)."""
    ia = a.index()
    names = [n for n in b.names if n in ia]
    jb = [b.index()[n] for n in names]
    ja = [ia[n] for n in names]
    return difference_test(a.z[ja], a.cov[np.ix_(ja, ja)], b.z[jb], b.cov[np.ix_(jb, jb)], names)
