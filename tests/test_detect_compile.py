"""Compiling the detector ahead: the synthetic image exercises the compiled path exactly."""

from __future__ import annotations

import pytest

from pipeline.stages.detect import precompile as detect_compile
from pipeline.stages.detect.detector import DetectConfig, detect_target


def test_synthetic_target_is_found_where_it_was_drawn() -> None:
    img = detect_compile.synthetic_target(96, 18.0)
    assert img.dtype.name == "uint8" and img.flags.c_contiguous
    det = detect_target(img, DetectConfig())
    assert det["found"] and det["reason"] == ""
    # drawn at (47.8, 47.6) with radius 18 (a binary disc: its area-equivalent diameter)
    assert det["u"] == pytest.approx(47.8, abs=0.05)
    assert det["v"] == pytest.approx(47.6, abs=0.05)
    assert det["s"] == pytest.approx(36.0, abs=0.5)


def test_compile_detector_warms_the_compiled_fine_stage() -> None:
    jit = pytest.importorskip("pipeline.stages.detect._jit")
    calls: list[int] = []
    took = detect_compile.compile_detector(
        DetectConfig(), on_slow=lambda: calls.append(1), after_s=600
    )
    assert took > 0 and not calls  # fast enough: no announcement
    assert jit.fine_stage.signatures and jit.coarse_uint8.signatures
    assert detect_compile.compile_detector(DetectConfig(compiled=False)) == 0.0
