"""Target grouping of touch-ups (``pipeline.stages.touchups.targets``)."""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.se3 import matrix_from_rpy
from pipeline.stages.touchups.targets import _best_hypothesis, group_targets


def _poses(
    seed: int, n_per: int, noise_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flange poses whose pin ``p`` touches one of three targets, in runs of ``n_per``."""
    rng = np.random.default_rng(seed)
    p = np.array([0.03, 0.006, 0.25])
    targets = np.array([[0.6, -0.2, 0.1], [0.7, 0.0, 0.1], [0.6, 0.2, 0.12]])
    Ts, labels = [], []
    for k, c in enumerate(targets):
        for _ in range(n_per):
            R = matrix_from_rpy(rng.normal(size=3) * 0.4)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = c - R @ p + rng.normal(scale=noise_m, size=3)
            Ts.append(T)
            labels.append(k)
    return np.array(Ts), np.array(labels), p


def _reference(R: np.ndarray, t: np.ndarray, hyps: np.ndarray, distinct: np.ndarray, eps: float):
    """One hypothesis at a time: lstsq, explicit distances (the definition)."""
    best, best_p = (-1, np.inf), np.zeros(3)
    for (i, j), (k, m) in hyps:
        A = np.concatenate([R[i] - R[j], R[k] - R[m]])
        b = np.concatenate([t[j] - t[i], t[m] - t[k]])
        p, *_ = np.linalg.lstsq(A, b, rcond=None)
        c = R @ p + t
        d = np.linalg.norm(c[:, None] - c[None], axis=-1)
        sc = (int(((d < eps) & distinct).any(axis=1).sum()), float(np.minimum(d, eps).sum()))
        if sc[0] > best[0] or (sc[0] == best[0] and sc[1] < best[1]):
            best, best_p = sc, p
    return best_p


def test_groups_three_targets_and_finds_the_pin() -> None:
    Ts, truth, p = _poses(1, 12, noise_m=2e-5)
    labels, p_est = group_targets(Ts, radius_m=0.02, ransac_samples=400, seed=0)
    np.testing.assert_array_equal(labels, truth)
    assert np.linalg.norm(p_est - p) < 1e-3


def test_batched_hypotheses_pick_the_one_at_a_time_winner() -> None:
    Ts, _, _ = _poses(2, 8, noise_m=5e-4)
    R, t = Ts[:, :3, :3], Ts[:, :3, 3]
    rng = np.random.default_rng(0)
    n = len(Ts)
    hyps = rng.integers(0, n, size=(300, 2, 2))
    hyps = hyps[(hyps[:, :, 0] != hyps[:, :, 1]).all(axis=1)]
    distinct = ~np.eye(n, dtype=bool)
    got = _best_hypothesis(R, t, hyps, distinct, 0.005)
    want = _reference(R, t, hyps, distinct, 0.005)
    np.testing.assert_allclose(got, want, atol=1e-9)
