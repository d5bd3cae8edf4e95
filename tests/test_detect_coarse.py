"""The compiled coarse pass equals the NumPy definition it replaces (subsample, median, extremes)."""

from __future__ import annotations

import numpy as np
import pytest

jit = pytest.importorskip("pipeline.stages.detect._jit")


@pytest.mark.parametrize("shape,k", [((512, 640), 4), ((37, 53), 3), ((9, 11), 2), ((100, 80), 5)])
def test_coarse_uint8_matches_numpy(shape: tuple[int, int], k: int) -> None:
    rng = np.random.default_rng(shape[0] * 7 + k)
    for order in ("C", "F"):
        img = np.asarray(rng.integers(0, 256, shape, dtype=np.uint8), order=order)
        img[rng.integers(0, shape[0]), :] = 3  # a dark line somewhere
        Hs, Ws = shape[0] // k, shape[1] // k
        small_ref = img[k // 2 : Hs * k : k, k // 2 : Ws * k : k]
        sub = small_ref[::2, ::2].ravel()
        bg_ref = float(np.partition(sub, sub.size // 2)[sub.size // 2])
        small, bg, lo, hi = jit.coarse_uint8(img, k)
        np.testing.assert_array_equal(small, small_ref)
        assert bg == bg_ref
        assert (lo, hi) == (float(small_ref.min()), float(small_ref.max()))
