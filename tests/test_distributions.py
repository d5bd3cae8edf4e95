"""The F and chi-square tails vtcal computes without importing scipy.stats."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from pipeline.estimation.distributions import chi2_ppf, f_sf


@pytest.mark.parametrize("dfn, dfd", [(1, 1), (3, 10), (3, 97), (8, 200), (2.5, 40.0)])
def test_f_sf_is_scipy_stats(dfn: float, dfd: float) -> None:
    xs = [-1.0, 0.0, 1e-12, 0.3, 1.0, 2.7, 10.0, 1e3, 1e9, math.inf]
    for x in xs:
        assert f_sf(x, dfn, dfd) == float(stats.f.sf(x, dfn, dfd)), x
    assert math.isnan(f_sf(math.nan, dfn, dfd)) and math.isnan(
        float(stats.f.sf(math.nan, dfn, dfd))
    )


def test_f_sf_of_no_degrees_of_freedom_is_nan() -> None:
    assert math.isnan(f_sf(1.0, 3, 0)) and math.isnan(float(stats.f.sf(1.0, 3, 0)))


@pytest.mark.parametrize("p", [0.5, 0.9, 0.975, 0.999])
@pytest.mark.parametrize("df", [1, 3, 6.5])
def test_chi2_ppf_is_scipy_stats(p: float, df: float) -> None:
    assert chi2_ppf(p, df) == float(stats.chi2.ppf(p, df))
    np.testing.assert_allclose(chi2_ppf(0.975, 3), 9.348403604496148, rtol=1e-15)
