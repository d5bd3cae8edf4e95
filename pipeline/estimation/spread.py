"""How far one calibration's true error may fall from the RMS its covariance predicts.

The covariance predicts the *expected* mean-square pin error over the workspace
poses (:func:`pipeline.estimation.uncertainty.predicted_errors`). One calibration is
one draw: its parameter error ``dz ~ N(0, cov)`` is fixed, and the mean square of
the error field it leaves over ``W`` poses, with ``G = Pr J_w`` the registered field
(:func:`pipeline.estimation.uncertainty.registered_field`) and ``cov = L L^T``, is::

    T^2 = |G dz|^2 / W = z^T M z,   M = L^T G^T G L / W,   z ~ N(0, I)          (Q1)
    T^2 = sum_i lambda_i chi2_1,i,  E[T^2] = sum_i lambda_i = rms_pred^2

(``lambda_i`` the eigenvalues of ``M``): a weighted sum of independent chi-squares,
which a few directions of the parameters dominate where the touch-ups fix a
combination poorly (on the simulated LR Mate-like cell with the ``full`` model one
direction carries most of it). Satterthwaite's approximation (Satterthwaite 1946)
matches its first two moments with a scaled chi-square of ``k`` degrees of freedom::

    T^2 ~ (rms_pred^2 / k) chi2_k,   k = (sum lambda)^2 / sum lambda^2              (Q2)

so the true RMS error lies, with probability ``1 - a``, in::

    rms_pred sqrt(chi2_k(a/2) / k)  ..  rms_pred sqrt(chi2_k(1 - a/2) / k)           (Q3)

and the figure ``rms_pred`` lies within 0.5-2x of it with probability::

    P_2x = P(k/4 <= chi2_k <= 4k)                                                    (Q4)

(0.69 at ``k = 1.5``, 0.91 at ``k = 4``, 0.98 at ``k = 8``). A covariance that is
exactly right still misses the 0.5-2x band on a share ``1 - P_2x`` of calibrations:
the benchmarks count the hits they expect from (Q4) beside the hits they observe.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.stats import chi2

from pipeline.kinematics.se3 import F64

#: the probability the range (Q3) holds the true RMS error
RANGE_LEVEL = 0.9


def error_spread(G: F64, cov: F64) -> dict[str, Any]:
    """(Q1)-(Q4): the effective degrees of freedom and the range of the true RMS error.

    Parameters
    ----------
    G : (3N, p) the registered pin error field over ``N`` workspace poses
        (:func:`pipeline.estimation.uncertainty.registered_field`; columns of ``cov``)
    cov : (p, p) covariance of those columns (m^2, rad^2)

    Returns
    -------
    dict (JSON-able): ``dof`` ``k`` of (Q2), ``range_factor`` ``[lo, hi]`` of (Q3) as
    multiples of the predicted RMS (at :data:`RANGE_LEVEL`), ``p_within_2x`` (Q4);
    NaN figures where the covariance is unusable or zero.
    """
    nan: dict[str, Any] = {
        "dof": float("nan"),
        "range_factor": [float("nan"), float("nan")],
        "p_within_2x": float("nan"),
    }
    cov = np.asarray(cov, dtype=float)
    if not np.all(np.isfinite(cov)):
        return nan
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    GL = G @ L
    lam = np.clip(np.linalg.eigvalsh(GL.T @ GL / (len(G) // 3)), 0.0, None)
    total, square = float(lam.sum()), float((lam**2).sum())
    if not total > 0.0:
        return nan
    k = total * total / square
    a = 1.0 - RANGE_LEVEL
    lo, hi = np.sqrt(chi2.ppf([a / 2.0, 1.0 - a / 2.0], k) / k)
    within = float(chi2.cdf(4.0 * k, k) - chi2.cdf(k / 4.0, k))
    return {"dof": float(k), "range_factor": [float(lo), float(hi)], "p_within_2x": within}
