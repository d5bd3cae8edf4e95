"""The Mitsuba image source (:mod:`pipeline.sim.render_pbr`) and the simulator's image-source hook."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.kinematics.se3 import transform_from
from pipeline.sim.camera import CameraModel
from pipeline.sim.cell import R_CAMERA_UNTILTED
from pipeline.sim.target_geometry import projected_ellipse
from pipeline.stages.detect.detector import DetectConfig, detect_target

REPO = Path(__file__).resolve().parent.parent
#: a small camera (200 x 160 px, the 10 mm target about 29 px across at 0.17 m)
CAM = CameraModel(fx=500.0, fy=500.0, cx=101.3, cy=78.6, k1=-0.07, k2=0.008, width=200, height=160)


def _pose() -> np.ndarray:
    """A plate tilted 20 deg about the camera's x axis, off the optical axis."""
    a = np.radians(20.0)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    return transform_from(R_CAMERA_UNTILTED @ Rx, np.array([0.004, -0.003, 0.17]))


def _source(effects: object) -> object:
    from pipeline.sim.render_pbr import PbrSettings, PbrSource

    return PbrSource(
        CAM, [(0, np.eye(4))], 0.010, 0.03, "dark_on_light", 0.17, 5, effects, PbrSettings()
    )


def test_mitsuba_render_centre_matches_projected_truth() -> None:
    """A noise-free linear render of a round print: vtcal's detector finds the centre of the
    exactly projected circle within 0.05 px and its long axis within 0.05 px."""
    pytest.importorskip("mitsuba")
    from pipeline.sim.render_pbr import PbrEffects

    eff = replace(PbrEffects.linear(), shot_noise=False, read_noise=False, prnu=False)
    src = _source(eff)
    T = _pose()
    img, grey = src.capture(0, T[None])  # type: ignore[attr-defined]
    assert img.dtype == np.uint8 and img.shape == (CAM.height, CAM.width)
    r = detect_target(grey, DetectConfig(polarity="dark_on_light"))
    u, v, s = projected_ellipse(CAM, T, 0.010)[:3]
    assert r["found"]
    assert abs(r["u"] - u) < 0.05 and abs(r["v"] - v) < 0.05, (r["u"], r["v"], u, v)
    assert abs(r["s"] - s) < 0.05, (r["s"], s)


def test_mitsuba_switches_change_the_image() -> None:
    """Defocus blurs the edge (lower edge gradient), sRGB brightens the dark ink; the
    linear twin's radiance does not depend on them being off twice."""
    pytest.importorskip("mitsuba")
    from pipeline.sim.render_pbr import PbrEffects

    base = replace(PbrEffects.linear(), shot_noise=False, read_noise=False, prnu=False)
    T = _pose()
    sharp = _source(base).radiance(0, T, 1)  # type: ignore[attr-defined]
    blurred = _source(replace(base, defocus=True)).radiance(0, T, 1)  # type: ignore[attr-defined]
    g_sharp = np.abs(np.diff(sharp, axis=1)).max()
    g_blur = np.abs(np.diff(blurred, axis=1)).max()
    assert g_blur < 0.8 * g_sharp, (g_blur, g_sharp)
    lin, _ = _source(base).sensor(sharp, np.random.default_rng(0))  # type: ignore[attr-defined]
    enc, _ = _source(replace(base, srgb=True)).sensor(sharp, np.random.default_rng(0))  # type: ignore[attr-defined]
    ink = sharp < 0.5 * sharp.max()
    assert enc[ink].mean() > lin[ink].mean() + 30


def test_session_image_source_forms_the_capture() -> None:
    """With ``Session.image_source`` set, the camera's capture is what the source formed
    (the simulator's own renderer is not called); unset, the simulator renders."""
    from pipeline.sim.cell_adapter import SimCell
    from pipeline.sim.scenario import load_scenario

    sc = load_scenario(REPO / "datasets" / "scenarios" / "small.toml")
    cell = SimCell.from_scenario(sc, 3)
    own = cell.camera.capture().image.copy()
    calls = []

    def source(tg: object, Ts: np.ndarray, opts: object) -> tuple[np.ndarray, np.ndarray]:
        calls.append(Ts.shape)
        img = np.full((sc.camera.height, sc.camera.width), 77, np.uint8)
        return img, img

    cell.sess.image_source = source
    got = cell.camera.capture().image
    assert calls and calls[0][1:] == (4, 4)
    assert np.all(got == 77) and not np.all(own == 77)
