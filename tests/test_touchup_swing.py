"""A touch-up's final centre freed of the camera's one-mode swing (touchup_swing)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.stages.touchups.rows import final_shapes
from pipeline.stages.touchups.swing import fit_one_mode, moment_globals, remove_swing
from pipeline.stages.touchups.types import Captures

DT = 0.21


def _swinging(
    n: int = 36, amp: float = 0.05, r: float = 0.5, delta_deg: float = 54.0, seed: int = 0
):
    """``n`` touch-ups of three captures ``DT`` apart: a true centre per touch-up, noise
    0.003 px, and a swing ``a r^k sin(phi + k Delta)`` along one random image direction
    with a random phase per touch-up (Delta off the fit's 10-degree grid)."""
    rng = np.random.default_rng(seed)
    truth = rng.normal(0.0, 1.0, (n, 2)) + (320.0, 240.0)
    u, v, t, uses = [], [], [], []
    for j in range(n):
        phi = rng.uniform(0, 2 * np.pi)
        ang = rng.uniform(0, 2 * np.pi)
        for k in range(3):
            off = amp * r**k * np.sin(phi + k * np.radians(delta_deg))
            u.append(truth[j, 0] + off * np.cos(ang) + rng.normal(0, 0.003))
            v.append(truth[j, 1] + off * np.sin(ang) + rng.normal(0, 0.003))
            t.append(10.0 * j + DT * k)
        uses.append([3 * j, 3 * j + 1, 3 * j + 2])
    return uses, np.array(t), np.array(u), np.array(v), truth


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(x**2, axis=1))))


def test_recovers_the_still_centre_of_a_one_mode_swing() -> None:
    uses, t, u, v, truth = _swinging()
    sw = remove_swing(uses, t, u, v)
    assert sw is not None and sorted(sw.centres) == list(range(len(uses)))
    got = np.array([sw.centres[k] for k in range(len(uses))])
    from pipeline.stages.touchups.settle import settle_weights, wmean

    w = settle_weights(uses, (u, v))
    weighted = np.array([[wmean(u, x, w), wmean(v, x, w)] for x in uses])
    err, err_w = _rms(got - truth), _rms(weighted - truth)
    # settle weights alone leave 0.0127 px RMS here (the swing still in the last
    # capture); the fit 0.0079 (seeds 0-3: 0.44-0.62x; 0.0056-0.0065 px at the truth's
    # decay and phase step, the noise's floor through the fit; 0.60-0.69x when the decay
    # and step were the least-squares grid's best instead of moment_globals')
    assert err < 0.65 * err_w, (err, err_w)
    assert abs(sw.spacing_s - DT) < 1e-9 and 0.35 <= sw.r <= 0.65
    assert abs(np.degrees(sw.delta) - 54.0) < 10.0


def test_the_pooled_differences_tell_the_decay_and_phase_step() -> None:
    """moment_globals (S2) recovers the arm's decay and phase step per capture, which the
    least-squares cost of (S1) barely tells (flat over the grid)."""
    for seed, (r, delta) in enumerate(((0.5, 54.0), (0.7, 100.0), (0.35, 30.0))):
        uses, t, u, v, _ = _swinging(n=400, r=r, delta_deg=delta, seed=seed)
        X = np.stack([u.reshape(-1, 3), v.reshape(-1, 3)], axis=2)
        got = moment_globals(X, 0.003**2, (0.6, np.radians(60.0)))
        assert got is not None
        assert abs(got[0] - r) < 0.06 and abs(np.degrees(got[1]) - delta) < 8.0, (got, r, delta)
        # the least-squares cost at the truth and at a wrong pair differ by little
        wrong = fit_one_mode(X, 0.8, np.radians(150.0))[0].sum()
        right = fit_one_mode(X, r, np.radians(delta))[0].sum()
        assert right < wrong < 3.0 * right


def test_not_used_with_too_few_touchups_and_uneven_ones_left_out() -> None:
    uses, t, u, v, _ = _swinging(n=9)
    assert remove_swing(uses, t, u, v) is None  # fewer than MIN_TOUCHUPS
    uses, t, u, v, _ = _swinging()
    t_odd = t.copy()
    t_odd[2] += 0.05  # touch-up 0's last capture 0.26 s after the one before
    u_nan = u.copy()
    u_nan[4] = np.nan  # touch-up 1's middle capture lost its centre
    short = [uses[0], uses[1], uses[2][1:], *uses[3:]]  # touch-up 2: two final captures
    sw = remove_swing(short, t_odd, u_nan, v)
    assert sw is not None and sorted(sw.centres) == list(range(3, len(uses)))
    t_all = t + np.random.default_rng(1).uniform(-0.06, 0.06, len(t))  # no common spacing
    assert remove_swing(uses, t_all, u, v) is None


def _captures(u: np.ndarray, v: np.ndarray, t: np.ndarray) -> Captures:
    n = len(u)
    df = pd.DataFrame(
        {"stamp_ns": (t * 1e9).astype(np.int64), "s_minor": np.full(n, 50.0), "angle": 0.1}
    )
    ok = np.ones(n, bool)
    s = np.full(n, 52.0)
    return Captures(df, [], np.zeros((n, 6)), np.zeros((n, 4, 4)), ok, ok, ok, u, v, s)


def test_the_touchup_stage_uses_it_only_for_a_swinging_camera() -> None:
    """final_shapes: a swinging camera's centres come from the one-mode fit (closer to the
    truth than the settle-weighted means); a still camera keeps its plain means, to the bit."""
    uses, t, u, v, truth = _swinging()
    finals = [np.array(x) for x in uses]
    _, shape, found = final_shapes(finals, _captures(u, v, t))
    assert found["centre"]["weighted"] and found["centre"]["swing"]["n"] == len(uses)
    from pipeline.stages.touchups.settle import settle_weights, wmean

    w = settle_weights(uses, (u, v))
    weighted = np.array([[wmean(u, x, w), wmean(v, x, w)] for x in uses])
    assert _rms(shape[:, :2] - truth) < 0.65 * _rms(weighted - truth)
    uses, t, u, v, truth = _swinging(amp=0.0)
    _, shape, found = final_shapes([np.array(x) for x in uses], _captures(u, v, t))
    assert not found["centre"]["weighted"] and "swing" not in found["centre"]
    plain = np.array([[np.mean(u[x]), np.mean(v[x])] for x in uses])
    assert np.array_equal(shape[:, :2], plain)
