"""Per-group variance components (pipeline.estimation.components, C1-C3) and their use
by identification (pipeline.stages.identify.components): recovered on data drawn with
known group variances, a test that holds its level where the groups are equal, and a
fit that weighs a noisy target down and lands nearer the truth for it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_accuracy,
    random_deviations,
    workspace_poses,
)
from pipeline.accuracy.evaluate import synthetic_touchups as synth
from pipeline.estimation.components import COMPONENT_ALPHA, group_components
from pipeline.kinematics.chain import load_chain
from pipeline.stages.identify.stage import IdentifyConfig, identify

URDF = (Path(__file__).resolve().parent.parent / "pipeline/robots/lrmate.urdf").read_text()
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]


def _regression(rng: np.random.Generator, sd: list[float], per: int = 40, p: int = 6):
    g = np.repeat(np.arange(len(sd)), per)
    A = rng.normal(size=(len(g), p))
    y = A @ rng.normal(size=p) + rng.normal(size=len(g)) * np.asarray(sd)[g]
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    return A, y - A @ x, g


def test_factors_recovered_and_redundancy_sums_to_m_minus_p() -> None:
    rng = np.random.default_rng(1)
    A, r, g = _regression(rng, [1.0, 3.0, 1.0], per=200)
    c = group_components(A, r, g)
    assert sum(c["dof"]) == pytest.approx(len(r) - A.shape[1], abs=1e-9)
    f = np.array(c["factor"])
    # pooled variance (1 + 9 + 1) / 3: factors 3/11, 27/11, 3/11
    assert f == pytest.approx([3 / 11, 27 / 11, 3 / 11], rel=0.2)
    assert c["p_value"] < 1e-10


def test_rows_in_no_group_are_left_out() -> None:
    rng = np.random.default_rng(2)
    A, r, g = _regression(rng, [1.0, 1.0], per=50)
    g = g.copy()
    g[:5] = -1
    c = group_components(A, r, g)
    assert len(c["factor"]) == 2 and np.all(np.isfinite(c["factor"]))
    one = group_components(A, r, np.where(g == 1, 1, -1))
    assert np.isnan(one["p_value"])  # a single group: nothing to compare


def test_bartlett_holds_its_level_where_the_groups_are_equal() -> None:
    rng = np.random.default_rng(3)
    p = [
        group_components(*_regression(rng, [1.0, 1.0, 1.0], per=24))["p_value"] for _ in range(600)
    ]
    rate = float(np.mean(np.asarray(p) < COMPONENT_ALPHA))
    assert rate <= 0.025  # 1 % nominal; 600 draws
    assert 0.4 < float(np.median(p)) < 0.6  # uniform under the null


def _cell(seed: int, loud: float):  # type: ignore[no-untyped-def]
    chain = load_chain(URDF, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(chain, random_deviations(chain, rng))
    tab, tg = synth(true, PIN, 4, 12, rng, noise_pin_m=2e-5, q_centre=Q_CENTRE)
    # the first target's touch-ups miss by `loud` more (as residual corrections would)
    rows = tab["target_id"].to_numpy() == tab["target_id"].iloc[0]
    for c in ("dx_flange", "dy_flange", "dz_flange"):
        tab.loc[rows, c] = tab.loc[rows, c] + rng.normal(scale=loud, size=int(rows.sum()))
    dist = [(0, 2, float(np.linalg.norm(tg[0] - tg[2])))]
    return tab, true, dist


def _abs_error(res, true, q) -> float:  # type: ignore[no-untyped-def]
    return float(pin_accuracy(res.chain, res.p_flange_pin, true, PIN, q)["abs_rms_m"])


def test_a_noisy_target_is_weighed_down_and_the_fit_is_better_for_it() -> None:
    """Twelve cells, one target 6x noisier: weighed apart, the true error's RMS over the
    cells halves, and the covariance's claim follows the truth (it did not before)."""
    true_err: dict[str, list[float]] = {"auto": [], "off": []}
    claims: dict[str, list[float]] = {"auto": [], "off": []}
    for seed in range(11, 23):
        tab, true, dist = _cell(seed, loud=1.2e-4)
        q = workspace_poses(
            tab[[c for c in tab.columns if c.startswith("joint")]].to_numpy(),
            300,
            np.random.default_rng(0),
        )
        for mode in ("auto", "off"):
            cfg = IdentifyConfig(model="mdh", distances=dist, target_components=mode)
            res = identify(tab, URDF, "base_link", "flange", cfg)
            vc = res.summary["variance_components"]
            if mode == "auto":
                assert vc["applied"] and vc["spent"] == 3
                w = np.asarray(vc["weights"])
                assert w[0] < 0.2 * np.min(w[1:])
            else:
                assert vc is None
            true_err[mode].append(_abs_error(res, true, q))
            claims[mode].append(res.summary["predicted_absolute_rms_mm"] * 1e-3)

    def rms(a: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(a))))

    assert rms(true_err["off"]) > 1.6 * rms(true_err["auto"])  # measured 2.2x
    assert 0.8 < rms(claims["auto"]) / rms(true_err["auto"]) < 1.3  # measured 1.14


def test_by_default_the_components_are_reported_and_the_fit_left_alone() -> None:
    tab, _, dist = _cell(11, loud=1.2e-4)
    cfg = IdentifyConfig(model="mdh", distances=dist)
    assert cfg.target_components == "report"
    vc = identify(tab, URDF, "base_link", "flange", cfg).summary["variance_components"]
    assert vc["p_value"] < 1e-10 and vc["factor"][0] > 2.0  # seen (3.5)
    assert not vc["applied"] and vc["weights"] == [1.0] * 4 and vc["spent"] == 0  # not acted on


def test_equal_targets_are_left_alone() -> None:
    tab, _, dist = _cell(21, loud=0.0)
    cfg = IdentifyConfig(model="mdh", distances=dist, target_components="auto")
    vc = identify(tab, URDF, "base_link", "flange", cfg).summary["variance_components"]
    assert vc["p_value"] > COMPONENT_ALPHA and not vc["applied"] and vc["spent"] == 0
    assert vc["weights"] == [1.0] * 4
