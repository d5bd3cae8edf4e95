"""Detection accuracy on simulated images against the exact projected ellipse.

Prints, per condition (target size, plate tilt, polarity, raw or PNG), the
RMS error of the centre and the relative RMS error of the long axis for

- vtcal's detector (:func:`pipeline.stages.detect.detector.detect_target`),
- plain ``cv2.fitEllipse`` on the contour of the image thresholded halfway
  between the two grey levels,

next to the Cramer-Rao bound for that noise and blur, and the ratio of
vtcal's RMS to the bound. Images come from the simulator's renderer
(:func:`pipeline.sim.render.render_target_image`: area coverage, Gaussian blur,
vignetting, grey noise, uint8) at its defaults (noise sigma 2, blur 0.7 px);
truth is :func:`pipeline.sim.target_geometry.projected_ellipse`.

Cramer-Rao bound: the image model ``g(x) = g_out + (g_in - g_out) Phi(-d(x) / w)``
with ``d`` the signed distance of pixel ``x`` to the ellipse
``(u, v, a, b, theta)`` and ``w^2 = blur^2 + 1/12`` (Gaussian blur of the
pixel-area-integrated edge), nuisance parameters ``g_out``, ``g_in``, ``w``;
Fisher information ``F = G^T G / sigma^2`` over all pixels, ``G`` the
derivatives of ``g`` (``dd/dparams`` from the normal of the foot point), bound
``sqrt(diag(F^-1))``; for ``s = 2a`` twice the bound of ``a``.

Usage: ``python benchmarks/bench_detect.py [N_PER_CONDITION]``
"""

from __future__ import annotations

import sys
import time

import cv2
import numpy as np
from scipy.special import ndtr

from pipeline.kinematics.se3 import matrix_from_rpy
from pipeline.sim.camera import CameraModel
from pipeline.sim.render import render_target_image
from pipeline.sim.target_geometry import projected_ellipse
from pipeline.stages.detect.detector import (
    DetectConfig,
    detect_target,
    ellipse_foot,
    ellipse_normals,
)

CAM = CameraModel(fx=912.0, fy=912.0, cx=317.6, cy=254.2, k1=-0.068, k2=0.0067)
NOISE, BLUR, D = 2.0, 0.7, 0.01


def pose(rng: np.random.Generator, z: float, tilt_deg: float) -> np.ndarray:
    t = np.radians(tilt_deg)
    d = rng.uniform(0, 2 * np.pi)
    T = np.eye(4)
    T[:3, :3] = matrix_from_rpy([np.pi + t * np.cos(d), t * np.sin(d), 0.0]) @ matrix_from_rpy(
        [0.0, 0.0, rng.uniform(0, 2 * np.pi)]
    )
    T[:3, 3] = [rng.uniform(-0.01, 0.01) * z / 0.17, rng.uniform(-0.01, 0.01) * z / 0.17, z]
    return T


def crb(ell: tuple[float, float, float, float, float], g_in: float, g_out: float) -> np.ndarray:
    """Cramer-Rao standard deviations of (u, v, s) for the blurred-edge model."""
    u0, v0, a, b, th = ell
    w = np.sqrt(BLUR**2 + 1.0 / 12.0)
    r = int(a) + 8
    vv, uu = np.mgrid[int(v0) - r : int(v0) + r + 1, int(u0) - r : int(u0) + r + 1]
    pts = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
    p = (u0, v0, a / 2, b / 2, th)
    p = (u0, v0, ell[2] / 2, ell[3] / 2, th)
    d, t, _ = ellipse_foot(pts, p, newton=6)
    n = ellipse_normals(p, t)
    c, s = np.cos(th), np.sin(th)
    ct, st = np.cos(t), np.sin(t)
    dd = -np.stack(
        [
            n[:, 0],
            n[:, 1],
            n[:, 0] * c * ct + n[:, 1] * s * ct,
            -n[:, 0] * s * st + n[:, 1] * c * st,
            n[:, 0] * (-s * p[2] * ct - c * p[3] * st) + n[:, 1] * (c * p[2] * ct - s * p[3] * st),
        ],
        axis=1,
    )
    z = d / w
    pdf = np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi)
    dg_dd = -(g_in - g_out) * pdf / w
    G = np.concatenate(
        [
            dg_dd[:, None] * dd,
            (1.0 - ndtr(-z))[:, None],  # d/d g_out
            ndtr(-z)[:, None],  # d/d g_in
            ((g_in - g_out) * pdf * z / w)[:, None],  # d/d w
        ],
        axis=1,
    )
    F = G.T @ G / NOISE**2
    cov = np.linalg.inv(F)
    sd = np.sqrt(np.diag(cov))
    return np.array([sd[0], sd[1], 2 * sd[2]])


def cv_fit(
    img: np.ndarray, levels: tuple[float, float], near: tuple[float, float]
) -> tuple[float, float, float] | None:
    """Plain OpenCV: threshold halfway between the (known) levels, fitEllipse on the contour.

    Favoured: it is given the true levels and takes the contour nearest the true centre.
    """
    thr = 0.5 * (levels[0] + levels[1])
    dark = levels[0] < levels[1]
    mask = ((img < thr) if dark else (img > thr)).astype(np.uint8)
    cnts, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    best = None
    for cnt in cnts:
        if len(cnt) < 5:
            continue
        (cu, cv_), (w1, w2), _ = cv2.fitEllipse(cnt)
        dist = float(np.hypot(cu - near[0], cv_ - near[1]))
        if best is None or dist < best[0]:
            best = (dist, cu, cv_, max(w1, w2))
    return None if best is None else (best[1], best[2], best[3])


def main() -> None:
    n_per = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    rng = np.random.default_rng(2024)
    conds = []
    for z in (0.30, 0.17, 0.11):
        for tilt in (0.0, 25.0, 45.0):
            for pol in ("dark_on_light", "light_on_dark"):
                conds.append((z, tilt, pol))
    print(
        f"noise sigma {NOISE} grey, blur {BLUR} px, {n_per} images per condition; "
        "errors against the exact projected ellipse"
    )
    hdr = (
        f"{'s_px':>6} {'tilt':>5} {'polarity':>14} {'img':>4} | {'vtcal c_rms':>11} "
        f"{'s_rel%':>7} | {'cv2 c_rms':>9} {'s_rel%':>7} | {'CRB c':>7} {'CRB s%':>7} | "
        f"{'ratio c':>7} {'ratio s':>7}"
    )
    print(hdr)
    all_c, all_s, all_cv_c, all_cv_s = [], [], [], []
    t_det = 0.0
    n_det = 0
    for z, tilt, pol in conds:
        levels = (40.0, 200.0) if pol == "dark_on_light" else (200.0, 40.0)
        per: dict[str, list[list[float]]] = {"raw": [], "png": []}
        cvs: list[list[float]] = []
        bounds = []
        for _ in range(n_per):
            T = pose(rng, z, tilt)
            img = render_target_image(CAM, T, D, levels=levels, rng=rng)
            ell = projected_ellipse(CAM, T, D)
            bounds.append(crb(ell, levels[0], levels[1]))
            ok, buf = cv2.imencode(".png", img)
            png = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
            for kind, im in (("raw", img), ("png", png)):
                t0 = time.perf_counter()
                r = detect_target(im, DetectConfig(polarity=pol))
                t_det += time.perf_counter() - t0
                n_det += 1
                per[kind].append([r["u"] - ell[0], r["v"] - ell[1], (r["s"] - ell[2]) / ell[2]])
            c = cv_fit(img, levels, (ell[0], ell[1]))
            if c is not None:
                cvs.append([c[0] - ell[0], c[1] - ell[1], (c[2] - ell[2]) / ell[2]])
        b = np.sqrt(np.mean(np.square(bounds), axis=0))
        s_mean = 2 * CAM.fx * 0.005 / z
        cv_a = np.array(cvs)
        cv_c = float(np.sqrt(np.mean(cv_a[:, 0] ** 2 + cv_a[:, 1] ** 2) / 2))
        cv_s = float(np.sqrt(np.mean(cv_a[:, 2] ** 2))) * 100
        for kind in ("raw", "png"):
            e = np.array(per[kind])
            c_rms = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2) / 2))
            s_rel = float(np.sqrt(np.mean(e[:, 2] ** 2))) * 100
            crb_c = float(np.sqrt((b[0] ** 2 + b[1] ** 2) / 2))
            crb_s = float(b[2] / s_mean) * 100
            print(
                f"{s_mean:6.1f} {tilt:5.0f} {pol:>14} {kind:>4} | {c_rms:11.4f} {s_rel:7.4f} | "
                f"{cv_c:9.4f} {cv_s:7.3f} | {crb_c:7.4f} {crb_s:7.4f} | "
                f"{c_rms / crb_c:7.2f} {s_rel / crb_s:7.2f}"
            )
            if kind == "raw":
                all_c.append(c_rms)
                all_s.append(s_rel)
                all_cv_c.append(cv_c)
                all_cv_s.append(cv_s)
    print(
        f"overall (raw): vtcal centre RMS {np.sqrt(np.mean(np.square(all_c))):.4f} px "
        f"(must be < 0.02), long axis {np.sqrt(np.mean(np.square(all_s))):.4f} % "
        f"(must be < 0.03); worst condition {max(all_c):.4f} px, {max(all_s):.4f} %"
    )
    print(
        f"overall (raw): cv2.fitEllipse centre RMS {np.sqrt(np.mean(np.square(all_cv_c))):.4f} px,"
        f" long axis {np.sqrt(np.mean(np.square(all_cv_s))):.3f} %"
    )
    print(f"detection time {1e3 * t_det / n_det:.2f} ms per 640x512 image")


if __name__ == "__main__":
    main()
