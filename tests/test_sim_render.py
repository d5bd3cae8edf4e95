"""Simulator camera model and renderer: exact geometry, accurate area coverage."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.kinematics.se3 import transform_from_xyz_rpy
from pipeline.sim.camera import CameraModel
from pipeline.sim.render import render_ideal, render_target_image
from pipeline.sim.target_geometry import fit_ellipse, projected_ellipse

CAM0 = CameraModel(900.0, 900.0, 318.3, 254.1, 0.0, 0.0, 640, 512)
CAMD = CameraModel(900.0, 905.0, 321.2, 250.7, -0.07, 0.007, 640, 512)


def test_undistort_inverts_distort() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.4, 0.4, size=(500, 2))
    back = CAMD.undistort(CAMD.distort(xy))
    assert np.max(np.abs(back - xy)) < 1e-12


def test_project_matches_opencv() -> None:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-0.05, 0.05, (50, 2)), rng.uniform(0.1, 0.3, 50)])
    K = np.array([[CAMD.fx, 0, CAMD.cx], [0, CAMD.fy, CAMD.cy], [0, 0, 1]])
    dist = np.array([CAMD.k1, CAMD.k2, 0, 0, 0])
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, dist)
    assert np.max(np.abs(CAMD.project(p) - ref[:, 0, :])) < 1e-9


def test_fit_ellipse_recovers_known_ellipse() -> None:
    a = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    ang = 0.3
    x, y = 20.0 * np.cos(a), 7.0 * np.sin(a)
    pts = np.column_stack(
        [100 + np.cos(ang) * x - np.sin(ang) * y, 50 + np.sin(ang) * x + np.cos(ang) * y]
    )
    u, v, L, S, th = fit_ellipse(pts)
    assert np.allclose([u, v, L, S, th], [100, 50, 40, 14, ang], atol=1e-9)


@pytest.mark.parametrize("depth", [0.12, 0.17, 0.25])
def test_long_axis_follows_f_D_over_d(depth: float) -> None:
    """Face-on target (plate parallel to the image plane): s = f D / d exactly."""
    T = transform_from_xyz_rpy([0.004, -0.003, depth], [0.0, 0.0, 0.7])
    u, v, s, s_short, _ = projected_ellipse(CAM0, T, 0.010)
    assert s == pytest.approx(CAM0.fx * 0.010 / depth, rel=1e-9)
    assert s_short == pytest.approx(s, rel=1e-9)
    # and the rendered disc has the same size: 4 sqrt(lambda_max) of the grey moments,
    # corrected for the pixel's own second moment (1/12 px^2)
    img = render_ideal(CAM0, T, 0.010, levels=(40.0, 200.0))
    cu, cv, L, _ = _moments(img, u, v)
    assert L == pytest.approx(s, abs=0.01)
    assert abs(cu - u) < 0.003 and abs(cv - v) < 0.003


def _moments(img: np.ndarray, u0: float, v0: float) -> tuple[float, float, float, float]:
    w = np.clip((200.0 - img) / 160.0, 0.0, 1.0)
    vv, uu = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    w[(uu - u0) ** 2 + (vv - v0) ** 2 > 45**2] = 0.0
    m = w.sum()
    cu, cv = (w * uu).sum() / m, (w * vv).sum() / m
    c = np.cov(np.stack([uu.ravel() - cu, vv.ravel() - cv]), aweights=w.ravel(), bias=True)
    lam = np.linalg.eigvalsh(c - np.eye(2) / 12.0)
    return cu, cv, 4 * np.sqrt(lam[1]), 4 * np.sqrt(lam[0])


@pytest.mark.parametrize("tilt", [0.0, 0.35, 0.6])
def test_area_coverage_centre_is_exact_without_distortion(tilt: float) -> None:
    """Without distortion the contour is an exact ellipse; the coverage centroid must sit on it."""
    T = transform_from_xyz_rpy([0.003, -0.002, 0.17], [tilt, 0.2 * tilt, 0.4])
    u, v, L, S, _ = projected_ellipse(CAM0, T, 0.010)
    img = render_ideal(CAM0, T, 0.010, levels=(40.0, 200.0))
    cu, cv, L2, S2 = _moments(img, u, v)
    assert abs(cu - u) < 0.003 and abs(cv - v) < 0.003
    assert abs(L2 - L) < 0.01 and abs(S2 - S) < 0.01


def test_rendered_image_noise_and_polarity() -> None:
    T = transform_from_xyz_rpy([0.0, 0.0, 0.17], [0.2, 0.1, 0.0])
    u, v, *_ = projected_ellipse(CAMD, T, 0.010)
    rng = np.random.default_rng(3)
    dark = render_target_image(CAMD, T, 0.010, rng=rng)
    light = render_target_image(CAMD, T, 0.010, levels=(200.0, 40.0), rng=rng)
    assert dark.dtype == np.uint8 and dark.shape == (512, 640)
    iu, iv = int(round(u)), int(round(v))
    assert dark[iv, iu] < 60 and light[iv, iu] > 150
    # sensor noise sigma ~2 on the flat plate
    patch = dark[iv - 5 : iv + 5, iu + 60 : iu + 70].astype(float)
    assert 1.0 < patch.std() < 3.5
    # same rng seed -> identical image
    a = render_target_image(CAMD, T, 0.010, rng=np.random.default_rng(9))
    b = render_target_image(CAMD, T, 0.010, rng=np.random.default_rng(9))
    assert np.array_equal(a, b)


def test_virtual_pin_is_where_a_perfect_touch_up_puts_an_untilted_target() -> None:
    """The true pin: the untilted circle centred there images at exactly (u0, v0, s0)."""
    from pipeline.kinematics.se3 import transform_from
    from pipeline.sim.cell import R_CAMERA_UNTILTED, virtual_pin_camera

    D, s0, u0, v0 = 0.01, 53.31, 319.5, 255.5
    # no distortion: fx D / s0 on the ray of the designated pixel
    p0 = virtual_pin_camera(CAM0, u0, v0, s0, D)
    xu, yu = CAM0.pixel_to_normalised(np.array([u0, v0]))
    assert np.allclose(p0, CAM0.fx * D / s0 * np.array([xu, yu, 1.0]), atol=1e-10)
    # barrel distortion shrinks the disc's image: the target must come nearer
    cam = CameraModel(900.0, 900.0, 321.2, 250.7, -0.07, 0.007, 640, 512)
    p = virtual_pin_camera(cam, u0, v0, s0, D)
    e = projected_ellipse(cam, transform_from(R_CAMERA_UNTILTED, p), D)
    assert abs(e[0] - u0) < 1e-7 and abs(e[1] - v0) < 1e-7 and abs(e[2] - s0) < 1e-7
    z_pinhole = cam.fx * D / s0
    r2 = (D / 2 / z_pinhole) ** 2
    assert p[2] - z_pinhole == pytest.approx(z_pinhole * cam.k1 * r2, rel=0.1)  # ~ -11 um
