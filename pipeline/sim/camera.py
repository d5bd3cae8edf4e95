"""Pinhole camera with two-term radial distortion, as the simulator renders with it.

Camera frame: OpenCV axes (``x`` right, ``y`` down, ``z`` along the optical
axis). A point ``p_cam = (X, Y, Z)`` projects to

    x = X / Z,  y = Y / Z,  r^2 = x^2 + y^2
    x_d = x (1 + k1 r^2 + k2 r^4),  y_d = y (1 + k1 r^2 + k2 r^4)
    u = fx x_d + cx,  v = fy y_d + cy

(the radial part of the Brown-Conrady model, as in OpenCV's ``projectPoints``
with ``p1 = p2 = k3 = 0``). Pixel centres are at integer ``(u, v)``, ``(0, 0)``
being the centre of the top-left pixel, so the image centre is
``((width - 1) / 2, (height - 1) / 2)``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of the simulated camera.

    Attributes
    ----------
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (pixel-centre convention, see module doc).
    k1, k2 : float
        Radial distortion coefficients (``x_d = x (1 + k1 r^2 + k2 r^4)``).
    width, height : int
        Image size in pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    width: int = 640
    height: int = 512

    # ------------------------------------------------------------------ model
    def distort(self, xy: ArrayLike) -> F64:
        """Undistorted normalised coordinates ``(N, 2)`` -> distorted ``(N, 2)``."""
        xy = np.asarray(xy, dtype=float)
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        return xy * (1.0 + self.k1 * r2 + self.k2 * r2 * r2)

    def undistort(self, xy_d: ArrayLike, iterations: int = 8) -> F64:
        """Invert :meth:`distort` by Newton's method on the radius.

        Solves ``r (1 + k1 r^2 + k2 r^4) = r_d`` for ``r`` (the direction is
        unchanged by radial distortion); converges to machine precision in a
        few steps for the mild distortion of measuring lenses.

        Parameters
        ----------
        xy_d : (..., 2) distorted normalised coordinates.

        Returns
        -------
        (..., 2) undistorted normalised coordinates.
        """
        xy_d = np.asarray(xy_d, dtype=float)
        rd = np.sqrt(np.sum(xy_d * xy_d, axis=-1))
        if self.k1 == 0.0 and self.k2 == 0.0:
            return xy_d.copy()
        r = rd.copy()
        for _ in range(iterations):
            r2 = r * r
            f = r * (1.0 + self.k1 * r2 + self.k2 * r2 * r2) - rd
            fp = 1.0 + 3.0 * self.k1 * r2 + 5.0 * self.k2 * r2 * r2
            r = r - f / fp
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return xy_d * scale[..., None]

    def project(self, p_cam: ArrayLike) -> F64:
        """Project camera-frame points to pixels.

        Parameters
        ----------
        p_cam : (N, 3) or (3,) points in the camera frame (``Z > 0``).

        Returns
        -------
        (N, 2) or (2,) pixel coordinates ``(u, v)``.
        """
        p = np.asarray(p_cam, dtype=float)
        xy = p[..., :2] / p[..., 2:3]
        xd = self.distort(xy)
        return np.stack([self.fx * xd[..., 0] + self.cx, self.fy * xd[..., 1] + self.cy], axis=-1)

    def pixel_to_normalised(self, uv: ArrayLike) -> F64:
        """Pixels ``(..., 2)`` -> undistorted normalised coordinates ``(x, y)`` (ray ``(x, y, 1)``)."""
        uv = np.asarray(uv, dtype=float)
        xd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort(xd)

    def pixel_rays(self) -> F64:
        """Undistorted normalised coordinates of every pixel centre, ``(height, width, 2)``.

        Cached per camera (read-only array).
        """
        return _pixel_rays(self)

    # -------------------------------------------------------------- (de)serial
    def to_dict(self) -> dict[str, Any]:
        return {k: (float(v) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraModel:
        return cls(
            fx=float(d["fx"]),
            fy=float(d["fy"]),
            cx=float(d["cx"]),
            cy=float(d["cy"]),
            k1=float(d.get("k1", 0.0)),
            k2=float(d.get("k2", 0.0)),
            width=int(d.get("width", 640)),
            height=int(d.get("height", 512)),
        )


@lru_cache(maxsize=8)
def _pixel_rays(cam: CameraModel) -> F64:
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    rays = cam.pixel_to_normalised(np.stack([u, v], axis=-1))
    rays.setflags(write=False)
    return rays
