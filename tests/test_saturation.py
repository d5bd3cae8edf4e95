"""A clipped plate: the halfway contour recovered by the censored edge fit (saturation.py)."""

from __future__ import annotations

import numpy as np
import pytest
from test_response import renders

from pipeline.stages.detect.detector import DetectConfig, detect_target
from pipeline.stages.detect.saturation import fit_clipped_edge


def _errors(images, clip_correction: bool):
    cfg = DetectConfig(polarity="dark_on_light", response="linear", clip_correction=clip_correction)
    dets = [detect_target(img, cfg) for img, _ in images]
    return np.array([d["s"] - s for d, (_, s) in zip(dets, images, strict=True)]), dets


@pytest.mark.parametrize(
    ("gain", "worst_before", "bound_after"),
    [(1.3, -0.04, 0.035), (1.8, -0.7, 0.08), (3.0, -1.6, 0.25)],
)
def test_a_clipped_plate_no_longer_shrinks_the_long_axis(gain, worst_before, bound_after):
    """Plate at ``gain`` x 200 grey, clipped at 255: halfway grey reads the disc small.

    Measured (seed 11, 50 px discs, blur 0.7 px): before -0.06, -0.82, -1.79 px; after
    -0.02, -0.01..-0.07, -0.05..-0.24 px. The last is a plate 2.35x the clip level, where only
    the dark third of the edge is seen and the pixel's box makes its tail not quite
    Gaussian.
    """
    images = renders(lambda E: np.clip(gain * E, 0.0, 1.0), n=6, seed=11, noise=1.0)
    before, _ = _errors(images, clip_correction=False)
    after, dets = _errors(images, clip_correction=True)
    assert before.max() < worst_before, before
    assert np.abs(after).max() < bound_after, (before, after)
    assert np.abs(after).max() < 0.5 * np.abs(before).min()
    assert all(d["clip_correction_px"] > 0.0 for d in dets)


def test_an_unclipped_plate_is_left_exactly_as_it_was():
    images = renders(lambda E: E, n=4, seed=12, noise=1.0)
    before, _ = _errors(images, clip_correction=False)
    after, dets = _errors(images, clip_correction=True)
    assert np.array_equal(before, after)
    assert all(d["clip_correction_px"] == 0.0 for d in dets)


def test_the_fit_recovers_the_plate_it_did_not_see():
    """A synthetic edge profile: the fit's plate level and blur are the truth's."""
    from scipy.special import ndtr

    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:100, 0:100].astype(float)
    r = np.hypot(xx - 50.2, yy - 49.7)
    grey = 30.0 + (520.0 - 30.0) * ndtr((r - 25.0) / 1.2) + rng.normal(0, 0.5, r.shape)
    img = np.clip(np.rint(grey), 0, 255)
    # the contour the halfway-grey detector sees: (30 + 255) / 2 is crossed at
    # r = 25 + 1.2 Phi^-1((142.5 - 30) / 490)
    from scipy.special import ndtri

    r_seen = 25.0 + 1.2 * float(ndtri((0.5 * (30.0 + 255.0) - 30.0) / 490.0))
    fit = fit_clipped_edge(img, 0.0, 0.0, (50.2, 49.7, r_seen, r_seen, 0.0), 1.0, 255.0)
    assert fit.ok
    assert fit.delta_px == pytest.approx(25.0 - r_seen, abs=0.01)
    assert fit.plate_level == pytest.approx(520.0, rel=0.02)
    assert fit.sigma_px == pytest.approx(1.2, rel=0.02)
    # a clipped bright target on a dark plate: its halfway contour lies outside
    bright = np.clip(np.rint(30.0 + 520.0 - grey), 0, 255)
    r_out = 25.0 - 1.2 * float(ndtri((0.5 * (30.0 + 255.0) - 30.0) / 490.0))
    fit = fit_clipped_edge(bright, 0.0, 0.0, (50.2, 49.7, r_out, r_out, 0.0), 1.0, 255.0, False)
    assert fit.ok and fit.delta_px == pytest.approx(25.0 - r_out, abs=0.01)
