"""How far one calibration's true error falls from the covariance figure (pipeline.estimation.spread).

Draws parameter errors from the covariance itself and checks that (Q3)'s range and
(Q4)'s chance of landing within 0.5-2x describe the draws' realised RMS errors.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.verdict import spread_mm, verdict
from pipeline.estimation.spread import RANGE_LEVEL, error_spread
from pipeline.estimation.uncertainty import predicted_errors, registered_field


def _field(rng: np.random.Generator, n_poses: int = 60, n_par: int = 8):
    p = rng.normal(scale=0.3, size=(n_poses, 3))
    Jw = rng.normal(size=(n_poses, 3, n_par))
    return Jw, p


def _realised(Jw, cov, p, kind, rng, n_draws=4000):
    G = registered_field(Jw, p, kind)
    L = np.linalg.cholesky(cov + 1e-18 * np.eye(len(cov)))
    dz = rng.normal(size=(n_draws, len(cov))) @ L.T
    return np.sqrt(np.sum((dz @ G.T) ** 2, axis=1) / len(p))


@pytest.mark.parametrize("weights", [[1.0] + [1e-4] * 7, [1.0, 0.5, 0.2] + [1e-3] * 5, [1.0] * 8])
def test_range_and_chance_describe_draws_from_the_covariance(weights):
    rng = np.random.default_rng(3)
    Jw, p = _field(rng)
    Q, _ = np.linalg.qr(rng.normal(size=(8, 8)))
    cov = (Q * np.asarray(weights) * 1e-10) @ Q.T
    sp = error_spread(registered_field(Jw, p, "absolute"), cov)
    rms = float(np.sqrt(np.mean(predicted_errors(Jw, cov, p, "absolute") ** 2)))
    T = _realised(Jw, cov, p, "absolute", rng)
    # (Q1): the predicted RMS is the root of the draws' mean square
    assert np.sqrt(np.mean(T**2)) == pytest.approx(rms, rel=0.05)
    lo, hi = (rms * f for f in sp["range_factor"])
    inside = np.mean((T >= lo) & (T <= hi))
    assert inside == pytest.approx(RANGE_LEVEL, abs=0.04)
    within = np.mean((rms / T >= 0.5) & (rms / T <= 2.0))
    assert within == pytest.approx(sp["p_within_2x"], abs=0.04)


def test_degrees_of_freedom_count_the_dominating_directions():
    rng = np.random.default_rng(5)
    Jw, p = _field(rng, n_par=6)
    one = np.zeros((6, 6))
    one[2, 2] = 1e-10
    assert error_spread(registered_field(Jw, p, "shape"), one)["dof"] == pytest.approx(
        1.0, abs=1e-6
    )
    # six equal, independent directions through a generic field: close to six, never more
    k = error_spread(registered_field(Jw, p, "raw"), 1e-10 * np.eye(6))["dof"]
    assert 4.5 < k <= 6.0 + 1e-9
    assert np.isnan(error_spread(registered_field(Jw, p, "shape"), np.zeros((6, 6)))["dof"])


def test_the_verdict_names_the_range_around_the_covariance_figure():
    summary = {
        "best_model": "mdh",
        "scale_held": False,
        "predicted_absolute_rms_mm": 0.02,
        "predicted_absolute_spread": {"dof": 2.0, "range_factor": [0.2, 1.7], "p_within_2x": 0.76},
    }
    v = verdict(summary)
    assert v is not None
    assert v["predicted_range_mm"] == pytest.approx([0.004, 0.034])
    assert "90 % within 0.0040-0.0340 mm" in v["line"]
    assert v["p_within_2x"] == pytest.approx(0.76)
    assert spread_mm(0.02, {"range_factor": [float("nan"), 1.0]}) is None
    assert spread_mm(None, {"range_factor": [0.2, 1.7]}) is None
