"""Step 4 of rendering: the simple camera's optics and sensor, after the ideal image.

:func:`finish_image` turns the noise-free grey image of
:func:`pipeline.sim.render.render_ideal` into what the camera delivers:
image-space occluders painted over it (:func:`paint_occluders`), Gaussian blur,
vignetting ``1 - v (r / r_corner)^2``, exposure gain, sensor noise
``N(0, sigma^2)`` and quantisation to ``uint8``. With the scenario's
real-camera sensor on (:mod:`pipeline.sim.optics`) only the occluders are
painted here and the optics module forms the image.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.sim.camera import CameraModel

#: (u, v, semi_major_px, semi_minor_px, angle_rad, grey) image-space occluder.
Occluder = tuple[float, float, float, float, float, float]


def paint_occluders(img: np.ndarray, occluders: Sequence[Occluder]) -> np.ndarray:
    """Paint image-space elliptical occluders (soft edge about 3 px) over ``img`` ``(H, W)``.

    Works in ``img``'s precision (``float32`` for :func:`finish_image`).
    """
    if not occluders:
        return img
    H, W = img.shape
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
    for u, v, a, b, ang, grey in occluders:
        c, s = np.cos(ang), np.sin(ang)
        du, dv = uu - u, vv - v
        x = (c * du + s * dv) / a
        y = (-s * du + c * dv) / b
        r = np.sqrt(x * x + y * y)
        # soft edge about 3 px wide
        w = np.clip((1.0 - r) * min(a, b) / 3.0 + 0.5, 0.0, 1.0)
        img = img * (1 - w) + np.float32(grey) * w
    return img


def finish_image(
    ideal: F64,
    camera: CameraModel,
    *,
    blur_sigma_px: float = 0.7,
    noise_sigma: float = 2.0,
    vignetting: float = 0.15,
    exposure: float = 1.0,
    rng: np.random.Generator | None = None,
    occluders: Sequence[Occluder] = (),
) -> np.ndarray:
    """Optics and sensor (step 4): occluders, blur, vignetting, exposure, noise, ``uint8``."""
    img: np.ndarray = np.array(ideal, dtype=np.float32)
    H, W = img.shape
    img = paint_occluders(img, occluders)
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if vignetting:
        vv, uu = np.mgrid[0:H, 0:W].astype(np.float32)
        r2 = (uu - camera.cx) ** 2 + (vv - camera.cy) ** 2
        r2max = max(camera.cx, W - 1 - camera.cx) ** 2 + max(camera.cy, H - 1 - camera.cy) ** 2
        img = img * (1.0 - np.float32(vignetting) * (r2 / np.float32(r2max)))
    img = img * np.float32(exposure)
    if noise_sigma > 0:
        gen = rng if rng is not None else np.random.default_rng(0)
        img = img + gen.normal(0.0, noise_sigma, size=img.shape).astype(np.float32)
    out: np.ndarray = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return out
