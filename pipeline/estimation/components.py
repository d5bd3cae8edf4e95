"""Variance components of groups of residuals: one variance factor per group, and a test.

A least-squares fit weighs every touch-up alike (after the flange whitening of
:mod:`pipeline.estimation.whitening`). Touch-ups of one target may scatter more than
another's: a target seen from steeper views, further away, printed worse. Förstner's
estimator of variance components (Förstner 1979; Koch, *Parameter Estimation and
Hypothesis Testing in Linear Models*, sec. 3.6) gives each group ``g`` of rows its own
variance factor from the fit's whitened residuals ``r`` and the redundancy numbers,
the diagonal of ``I - H`` with ``H = A (A^T A)^-1 A^T`` the fit's hat matrix::

    f_g = sum_{i in g} (1 - h_ii),     s_g^2 = sum_{i in g} r_i^2 / f_g              (C1)

(``f_g`` the residual degrees of freedom group ``g`` holds: ``sum_g f_g`` over every row
is ``m - p``). Whether the groups differ at all is Bartlett's test of equal variances
on those degrees of freedom (Bartlett 1937), with ``f = sum f_g`` and ``s^2`` the pooled
``sum f_g s_g^2 / f``::

    B = [f ln s^2 - sum_g f_g ln s_g^2] / [1 + (sum_g 1/f_g - 1/f) / (3 (G - 1))]    (C2)

``B ~ chi2(G - 1)`` when the groups share one variance. Only when it rejects are the
groups weighed apart, each group's rows by ``s / s_g`` (Helmert's iteration: refit,
re-estimate, until the factors settle), and the ``G - 1`` ratios so estimated are
taken from the variance factor's degrees of freedom, as the whitening's are (W1)::

    f = m - p - 5 [whitened] - (G - 1) [components]                                 (C3)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.stats import chi2

from pipeline.kinematics.se3 import F64

#: the level at which Bartlett's test (C2) must reject before groups are weighed apart
COMPONENT_ALPHA = 0.01
#: a group needs at least this many residual degrees of freedom (C1) to have a factor
MIN_GROUP_DOF = 3.0


def group_components(A: F64, r: F64, groups: Any) -> dict[str, Any]:
    """(C1)-(C2): each group's variance factor and Bartlett's test that they are equal.

    Parameters
    ----------
    A : (m, p) the fit's (whitened) Jacobian over its estimated unknowns
    r : (m,) its (whitened) residuals at the solution
    groups : (m,) int group index per row; negative: a row in no group (constraints)

    Returns
    -------
    dict (JSON-able): ``dof`` (G,) ``f_g``, ``factor`` (G,) ``s_g^2 / s^2``, ``pooled``
    ``s^2``, ``bartlett`` ``B``, ``p_value``; ``p_value`` NaN with fewer than two groups
    holding :data:`MIN_GROUP_DOF`.
    """
    A = np.asarray(A, dtype=float)
    r = np.asarray(r, dtype=float)
    g = np.asarray(groups, dtype=int)
    Q, _ = np.linalg.qr(A)
    h = np.sum(Q * Q, axis=1)
    G = int(g.max()) + 1 if (g >= 0).any() else 0
    f = np.array([float(np.sum(1.0 - h[g == k])) for k in range(G)])
    ss = np.array([float(np.sum(r[g == k] ** 2)) for k in range(G)])
    ok = f >= MIN_GROUP_DOF
    out: dict[str, Any] = {
        "dof": f.tolist(),
        "factor": [float("nan")] * G,
        "pooled": float("nan"),
        "bartlett": float("nan"),
        "p_value": float("nan"),
    }
    if int(ok.sum()) < 2:
        return out
    s2 = ss[ok] / f[ok]
    ftot = float(f[ok].sum())
    pooled = float(ss[ok].sum() / ftot)
    if not pooled > 0.0 or not np.all(s2 > 0.0):
        return out
    k = int(ok.sum())
    c = 1.0 + (float(np.sum(1.0 / f[ok])) - 1.0 / ftot) / (3.0 * (k - 1))
    B = (ftot * math.log(pooled) - float(np.sum(f[ok] * np.log(s2)))) / c
    factor = np.full(G, np.nan)
    factor[ok] = s2 / pooled
    out.update(
        factor=factor.tolist(),
        pooled=pooled,
        bartlett=float(B),
        p_value=float(chi2.sf(B, k - 1)),
    )
    return out
