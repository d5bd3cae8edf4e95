"""vtcal's detector on real photographs (``datasets/real/dots``, Apache-2.0).

15 webcam photos of a printed 10x10 dot grid from a robot's wrist: real lens
distortion, real noise, a real print and a clipped white plate. No centre has a
ground truth; what is checked is consistency, with the functions
``benchmarks/bench_real_images.py`` measures with. The dot centres must fit one
camera model, their long axes must agree with the ones that model predicts, and
the detector must find the dots.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
DOTS = REPO / "datasets" / "real" / "dots"


def load_bench(name: str):
    """The module ``benchmarks/NAME.py`` (benchmarks are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _bench():
    return load_bench("bench_real_images")


@pytest.fixture(scope="module")
def measured():
    B = _bench()
    pitch = B.read_pitch()
    shots = B.photos()
    cv, vt = {}, {}
    for i, g in shots:
        c, s = B.opencv_blobs(g)
        cv[i] = (c, s)
        vt[i] = B.vtcal_dots(g, c, s, B.VTCAL_CONFIG)[0]
    return B, pitch, shots, cv, vt


def test_the_real_photos_are_shipped_with_their_licence():
    assert (DOTS / "LICENSE.industrial_calibration").read_text().startswith("Apache License")
    assert len(list((DOTS / "images").glob("*.png"))) == 15
    assert "industrial_calibration" in (REPO / "datasets" / "real" / "README.md").read_text()


def test_vtcal_finds_the_real_dots(measured):
    B, _, shots, _, vt = measured
    found = np.concatenate([vt[i][:, 0] == 1 for i, _ in shots])
    good = np.concatenate(
        [(vt[i][:, 0] == 1) & (vt[i][:, 6] <= B.MAX_RESIDUAL_PX) for i, _ in shots]
    )
    # measured: 1475 of 1500 within 0.25 px of fit residual
    assert found.mean() > 0.97 and good.mean() > 0.95, (found.mean(), good.mean())


def test_real_centres_fit_one_camera_as_well_as_opencvs(measured):
    B, _, shots, cv, vt = measured
    pitch = B.read_pitch()
    keep = {i: (vt[i][:, 0] == 1) & (vt[i][:, 6] <= B.MAX_RESIDUAL_PX) for i, _ in shots}
    objs = [B.grid_points(pitch)[keep[i]] for i, _ in shots]
    ours = B.calibrate(objs, [vt[i][keep[i], 1:3] for i, _ in shots], (640, 480))
    theirs = B.calibrate(objs, [cv[i][0][keep[i]] for i, _ in shots], (640, 480))
    # measured: 0.1939 px against OpenCV's 0.1874 (ratio 1.035; the goal of 0.5 is
    # not reached: most of the residual is common to every detector, see the benchmark)
    assert ours["rms"] < 0.25, ours["rms"]
    assert ours["rms"] < 1.15 * theirs["rms"], (ours["rms"], theirs["rms"])
    # the same camera from either detector's centres
    assert ours["K"][0, 0] == pytest.approx(theirs["K"][0, 0], rel=0.01)


def test_real_long_axes_agree_with_the_fitted_camera(measured):
    B, pitch, shots, cv, vt = measured
    keep = {i: (vt[i][:, 0] == 1) & (vt[i][:, 6] <= B.MAX_RESIDUAL_PX) for i, _ in shots}
    small = {i: keep[i] & (np.arange(100) != B.big_dot(cv[i][1])) for i, _ in shots}
    cal = B.calibrate(
        [B.grid_points(pitch)[keep[i]] for i, _ in shots],
        [vt[i][keep[i], 1:3] for i, _ in shots],
        (640, 480),
    )
    # the calibration's per-photo poses, with each photo's small dots
    ob = [B.grid_points(pitch)[small[i]] for i, _ in shots]
    meas = [vt[i][small[i], 3] for i, _ in shots]
    la = B.long_axis_fit(cal, ob, meas, pitch)
    # measured: 3.01 % RMS (the goal of 1 % is not reached: each photo's exposure
    # clips the white plate differently, -4.8 % to +4.2 % per photo); OpenCV's size: 5.01 %
    assert abs(la["mean"]) < 0.01 and la["rms"] < 0.04, la
    # the printed dots are about half the pitch
    assert 0.45 < la["rho"] < 0.55
