"""(P1): the touch-ups' unseen constant pin offset in the predicted errors and the verdict.

A constant offset ``b`` of every touch-up's pin (flange frame) is absorbed by the
pin, so no residual sees it; the calibrated pin is then off by ``b`` at every pose,
``R_base_flange b`` in the base frame. :func:`with_pin_offset` puts ``cov(b)`` into
the pin's covariance; here seeded draws of ``b`` are registered like the accuracy
figures and their mean square must match the propagated prediction.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.evaluate import registered_errors
from pipeline.accuracy.verdict import predicted_kind, verdict
from pipeline.estimation.uncertainty import predicted_errors, with_pin_offset
from pipeline.kinematics.se3 import matrix_from_axis_angle
from pipeline.stages.touchups.noise import pin_offset_cov


def _poses(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` flange orientations within a 40 deg cone and pin positions in a 0.3 m box."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R = np.stack(
        [matrix_from_axis_angle(a, t) for a, t in zip(axes, rng.uniform(0, 0.7, n), strict=True)]
    )
    p = rng.uniform(-0.15, 0.15, (n, 3))
    return R, p


def _sigma_pose() -> np.ndarray:
    """A pose component long along the view (flange z), as on the foreign recordings."""
    return np.diag([2e-6, 2e-6, 40e-6]) ** 2


def test_nothing_added_without_a_pose_component() -> None:
    cov = np.eye(6) * 1e-10
    assert with_pin_offset(cov, None) is cov
    nan = [[float("nan")] * 3] * 3
    assert np.array_equal(with_pin_offset(cov, nan), cov)
    assert np.array_equal(with_pin_offset(cov, [[1.0, 0.0], [0.0, 1.0]]), cov)


def test_only_the_pin_block_grows() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(7, 7)) * 1e-5
    cov = A @ A.T
    out = with_pin_offset(cov, _sigma_pose())
    assert np.array_equal(out[:4], cov[:4]) and np.array_equal(out[:, :4], cov[:, :4])
    assert out[4:, 4:] - cov[4:, 4:] == pytest.approx(_sigma_pose(), abs=1e-20)
    assert out is not cov and np.array_equal(cov, A @ A.T)  # the input is not changed


def test_raw_error_of_a_pin_offset_is_its_trace() -> None:
    """With nothing else uncertain, a pin offset moves every pose by ``|R b|``: the
    predicted raw error is ``sqrt(trace Sigma)`` at every pose."""
    rng = np.random.default_rng(4)
    R, p = _poses(rng, 50)
    Jw = np.concatenate([np.zeros((50, 3, 2)), R], axis=2)  # two kinematic columns, the pin
    cov = with_pin_offset(np.zeros((5, 5)), _sigma_pose())
    raw = predicted_errors(Jw, cov, p, "raw")
    assert raw == pytest.approx(np.full(50, np.sqrt(np.trace(_sigma_pose()))), rel=1e-12)


@pytest.mark.parametrize("kind", ["absolute", "shape"])
def test_registered_offsets_scatter_as_predicted(kind: str) -> None:
    """Seeded draws ``b ~ N(0, Sigma)``, the field ``R_i b`` registered (rigid or
    similarity) like the accuracy figures: their mean square error over the draws is
    the prediction's, to the Monte-Carlo error of 400 draws (about 7 % in RMS)."""
    rng = np.random.default_rng(5)
    R, p = _poses(rng, 60)
    Jw = np.concatenate([np.zeros((60, 3, 1)), R], axis=2)
    cov = with_pin_offset(np.zeros((4, 4)), _sigma_pose())
    pred = float(np.sqrt(np.mean(predicted_errors(Jw, cov, p, kind) ** 2)))
    L = np.linalg.cholesky(_sigma_pose())
    ms = [
        np.mean(registered_errors(p + R @ (L @ rng.normal(size=3)), p, scale=kind == "shape") ** 2)
        for _ in range(400)
    ]
    assert float(np.sqrt(np.mean(ms))) == pytest.approx(pred, rel=0.12)
    # the registration hides the mean orientation's share, not the rest (0.29x in a 40 deg cone)
    assert 0.1 * np.sqrt(np.trace(_sigma_pose())) < pred < np.sqrt(np.trace(_sigma_pose()))


def test_verdict_takes_the_absolute_figure_with_a_known_distance() -> None:
    base = {
        "model": "poe",
        "predicted_shape_rms_mm": 0.02,
        "predicted_absolute_rms_mm": 0.04,
        "rms_mm": 0.03,
    }
    assert predicted_kind({**base, "scale_held": False}) == "absolute"
    assert predicted_kind({**base, "scale_held": True}) == "shape"
    assert predicted_kind(base) == "shape"  # an older identify.json: as before
    v = verdict({**base, "scale_held": False})
    assert v is not None and v["validated_mm"] == 0.04 and v["predicted_kind"] == "absolute"
    v = verdict({**base, "scale_held": True})
    assert v is not None and v["validated_mm"] == 0.02 and "shape" in v["validated_how"]


def test_the_offset_only_where_the_pose_component_was_told_apart() -> None:
    """One capture per touch-up: the loop steps' component is one capture's whole noise,
    which averages over the touch-ups, so no pin offset is taken from it."""
    cov = (np.eye(3) * 1e-10).tolist()
    assert pin_offset_cov({"rms_touchup_um": 44.3, "cov_pose_flange_m2": cov}) == cov
    assert pin_offset_cov({"rms_touchup_um": float("nan"), "cov_pose_flange_m2": cov}) is None
    assert pin_offset_cov({"rms_touchup_um": 44.3, "cov_pose_flange_m2": [[1.0]]}) is None
    assert pin_offset_cov(None) is None and pin_offset_cov({}) is None


def test_pin_offset_left_keeps_what_the_residual_still_shows() -> None:
    """(P2): along each principal axis of the pose component, no more than the residual."""
    from pipeline.estimation.uncertainty import pin_offset_left

    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    P = (Q * np.array([1e-12, 2e-12, 9e-10])) @ Q.T  # 1, 1.4, 30 um along the view
    big = (Q * np.array([4e-12, 4e-12, 4e-9])) @ Q.T
    assert np.allclose(pin_offset_left(P, big), P, rtol=1e-9, atol=1e-24)
    small = (Q * np.array([4e-12, 4e-12, 1e-10])) @ Q.T  # the print shape took the rest
    left = np.asarray(pin_offset_left(P, small))
    lam = np.sort(np.linalg.eigvalsh(left))
    assert np.allclose(lam, [1e-12, 2e-12, 1e-10], rtol=1e-6)
    assert pin_offset_left(None, small) is None
    assert pin_offset_left(P, np.full((3, 3), np.nan)) is P
