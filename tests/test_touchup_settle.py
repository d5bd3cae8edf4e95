"""Weights of a touch-up's repeated final captures when the camera had not settled."""

from __future__ import annotations

import numpy as np

from pipeline.stages.touchups.settle import settle_weights, wmean


def _captures(swing: tuple[float, float, float], n: int = 36, seed: int = 0):
    """``n`` touch-ups of three captures: true centre 0, noise 0.004 px, and a swing of the
    given amplitude per capture (first to last) with one random direction per touch-up."""
    rng = np.random.default_rng(seed)
    u, v, uses = [], [], []
    for k in range(n):
        phi = rng.uniform(0, 2 * np.pi)
        for a in swing:
            u.append(a * np.cos(phi) + rng.normal(0, 0.004))
            v.append(a * np.sin(phi) + rng.normal(0, 0.004))
        uses.append([3 * k, 3 * k + 1, 3 * k + 2])
    return uses, np.array(u), np.array(v)


def test_a_still_camera_keeps_the_plain_mean() -> None:
    uses, u, v = _captures((0.0, 0.0, 0.0))
    assert settle_weights(uses, (u, v)) is None
    for use in uses[:5]:  # no weights: the plain mean, to the bit
        assert wmean(u, use, None) == float(np.mean(u[use]))
    assert settle_weights([use[:2] for use in uses], (u, v)) is None  # two captures: cannot tell


def test_a_swinging_camera_weighs_its_early_captures_less() -> None:
    uses, u, v = _captures((0.05, 0.02, 0.008))
    w = settle_weights(uses, (u, v))
    assert w is not None
    first, second, last = w[0::3], w[1::3], w[2::3]
    assert np.all(first < 0.1 * last) and np.all(second <= last)
    plain = np.hypot([np.mean(u[x]) for x in uses], [np.mean(v[x]) for x in uses])
    weighted = np.hypot([wmean(u, x, w) for x in uses], [wmean(v, x, w) for x in uses])
    assert np.sqrt(np.mean(weighted**2)) < 0.6 * np.sqrt(np.mean(plain**2))


def test_lost_touchups_and_short_blocks_are_taken_as_they_are() -> None:
    uses, u, v = _captures((0.05, 0.02, 0.008))
    uses = [[]] + [use[1:] for use in uses[:4]] + uses[4:]  # one lost, four with two captures
    w = settle_weights(uses, (u, v))
    assert w is not None and np.all(np.isfinite(w)) and np.all(w > 0)


def test_the_summary_says_what_the_weights_did() -> None:
    """settle_summary (touchups.parquet's ``vtcal.settle``, shown by the report) gives the
    scatter of each place against the last, the test and the weights settle_weights used."""
    from pipeline.stages.touchups.settle import settle_summary

    uses, u, v = _captures((0.05, 0.02, 0.008))
    sizes = (np.zeros_like(u) + np.random.default_rng(3).normal(0, 0.01, len(u)),)
    got = settle_summary(uses, (u, v), sizes)
    centre, size = got["centre"], got["size"]
    assert centre["tested"] and centre["weighted"] and centre["p_value"] < 1e-3
    # RMS per coordinate of (x_j - x_0): the first capture about 0.042 px from the last
    assert centre["scatter_px"][1] > 2 * centre["scatter_px"][0] > 0
    assert 0.03 < centre["scatter_px"][1] < 0.05
    w = settle_weights(uses, (u, v))
    assert w is not None
    assert np.allclose(centre["weights"], [w[2], w[1], w[0]])  # the last capture's first
    assert size["tested"] and not size["weighted"] and size["weights"] == []
    still = settle_summary(uses, (v * 0 + 1,), sizes)  # no scatter at all: D = 0
    assert not still["centre"]["weighted"]
    short = settle_summary([x[:2] for x in uses], (u, v), sizes)
    assert not short["centre"]["tested"] and not short["size"]["tested"]
