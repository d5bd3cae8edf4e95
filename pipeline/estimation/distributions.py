"""Tail probabilities of the F and chi-square distributions, without ``scipy.stats``.

``scipy.stats`` takes 0.2-0.3 s to import (every distribution object is built);
the tests vtcal makes need two functions of ``scipy.special``, which
``scipy.optimize`` has already imported. The values are the ones ``scipy.stats``
computes (it calls the same special functions; tested equal).
"""

from __future__ import annotations

import math

from scipy import special


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """``P(F > x)`` for ``F ~ F(dfn, dfd)``: ``scipy.stats.f.sf(x, dfn, dfd)``.

    ``fdtrc(dfn, dfd, x) = I_{dfd / (dfd + dfn x)}(dfd / 2, dfn / 2)`` (regularised
    incomplete beta) inside the support; 1 at or below 0, 0 at infinity, NaN for
    a NaN ``x`` or degrees of freedom that are not positive.
    """
    if not (dfn > 0 and dfd > 0) or math.isnan(x):
        return math.nan
    if x <= 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    return float(special.fdtrc(dfn, dfd, x))


def chi2_ppf(p: float, df: float) -> float:
    """The ``p`` quantile of the chi-square distribution with ``df`` degrees of freedom:
    ``2 P^-1(df / 2, p)`` with ``P`` the regularised lower incomplete gamma function
    (``scipy.stats.chi2.ppf(p, df)``)."""
    return float(2.0 * special.gammaincinv(df / 2.0, p))
