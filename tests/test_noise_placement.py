"""The long axis under an encoded response: the detector loses nothing to the curve.

``benchmarks/bench_noise_placement.py`` images one disc many times. With the
sensor noise before the response curve (as a real sensor's), the sRGB and
gamma 2.2 long axes scatter as the linear image's; with the simulator's noise
after the curve they scatter ~1.4x more, by the curve's slope at the contour.
"""

from __future__ import annotations

import numpy as np
from test_real_images import load_bench


def test_an_encoded_image_with_noise_before_the_curve_measures_as_a_linear_one() -> None:
    B = load_bench("bench_noise_placement")
    n = 80
    lin = B.long_axes("linear", 1.0, True, n)
    for kind, gamma in (("srgb", 1.0), ("gamma", 2.2)):
        enc = B.long_axes(kind, gamma, True, n)
        assert len(enc) == n and len(lin) == n
        assert enc.std(ddof=1) < 1.15 * lin.std(ddof=1), kind  # measured 0.99-1.00 at n=200
        assert abs(enc.mean() - lin.mean()) < 2e-3, kind  # no bias from the curve (px)
    after = B.long_axes("srgb", 1.0, False, n).std(ddof=1)
    lin_after = B.long_axes("linear", 1.0, False, n).std(ddof=1)
    assert after > 1.25 * lin_after  # the curve's slope on noise added after it (1.42)
    assert np.isfinite(after)
