"""The region a calibration holds for (pipeline.estimation.region, G1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.estimation.region import GROWTH_WARN, region_summary, widened_poses
from pipeline.stages.outliers.adequacy import trust


def test_widened_poses_reach_half_a_span_beyond_and_keep_to_the_limits():
    rng = np.random.default_rng(0)
    q = np.array([[0.0, -1.0], [1.0, 1.0], [0.5, 0.0]])
    w = widened_poses(q, np.array([-np.inf, -1.5]), np.array([np.inf, 1.5]), 4000, rng)
    assert w[:, 0].min() == pytest.approx(-0.5, abs=0.01)
    assert w[:, 0].max() == pytest.approx(1.5, abs=0.01)
    assert w[:, 1].min() >= -1.5 and w[:, 1].max() <= 1.5  # clipped to the limits
    assert w[:, 1].min() == pytest.approx(-1.5, abs=0.01)


def test_the_summary_names_the_ranges_and_warns_only_on_a_large_growth():
    q = np.radians([[-10.0, 20.0], [30.0, 50.0]])
    ok = region_summary(["j1", "j2"], q, 0.02, 0.05)
    assert ok["joint_ranges_deg"]["j1"] == pytest.approx([-10.0, 30.0])
    assert ok["growth"] == pytest.approx(2.5) and not ok["extrapolation_warning"]
    assert "j1 -10..+30 deg" in ok["note"] and "grows" not in ok["note"]
    bad = region_summary(["j1", "j2"], q, 0.02, 0.02 * (GROWTH_WARN + 1))
    assert bad["extrapolation_warning"] and "inside them" in bad["note"]
    s = {"rms_mm": 0.01, "dof": 30, "n_rows": 20, "region": bad}
    assert any("grows" in w for w in trust(s, None, None)["warnings"])
    assert math.isnan(region_summary(["j1", "j2"], q, 0.0, 0.1)["growth"])


def test_identify_reports_the_covered_ranges_of_the_touchups():
    from pipeline.accuracy.evaluate import perturbed_chain, random_deviations, synthetic_touchups
    from pipeline.kinematics import load_chain
    from pipeline.robots import builtin_urdf
    from pipeline.stages.identify.stage import IdentifyConfig, identify

    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(5)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    table, _ = synthetic_touchups(true, np.array([0.0, 0.0, 0.25]), 3, 8, rng, noise_pin_m=2e-6)
    res = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="mdh"))
    region = res.summary["region"]
    q = table[nominal.joint_names].to_numpy()
    lo = np.degrees(q.min(axis=0))
    assert [region["joint_ranges_deg"][n][0] for n in nominal.joint_names] == pytest.approx(lo)
    # a wider box than the touch-ups': the covariance predicts a larger error there
    assert region["predicted_beyond_mm"] > region["predicted_inside_mm"] > 0
