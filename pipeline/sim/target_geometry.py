"""The printed target's boundary and its exact image ellipse: the simulator's reference geometry.

:class:`PrintShape` is the boundary of a printed target disc (a perfect circle
by default); the renderer (:mod:`pipeline.sim.render`) uses it in every inside
test. :func:`projected_ellipse` is the reference geometry: many points of the
3-D circle (or printed boundary) projected through the same camera model, and
the ellipse fitted to them (:func:`fit_ellipse`: centre, full long and short
axes, long-axis angle). This is the contour the spec defines (boundary at the
grey level halfway between target and plate).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64
from pipeline.sim.camera import CameraModel


@dataclass(frozen=True)
class PrintShape:
    """Boundary of a printed target disc in the plate frame, ``r(phi)`` about its centre.

    An ellipse of semi-axes ``a = R (1 + e)``, ``b = R (1 - e)`` with its long
    axis at ``orientation_rad`` from the plate's ``x`` axis, plus edge roughness:

        r(phi) = a b / sqrt((b cos psi)^2 + (a sin psi)^2) + sum_k A_k cos(k phi + p_k),
        psi = phi - orientation

    (``phi`` the polar angle about the centre, m). ``e = 0`` and no harmonics is
    the perfect circle of radius ``R``. Drawn per target by
    :func:`pipeline.sim.optics.draw_print`.

    Attributes
    ----------
    radius_m : float
        ``R`` (half the mean printed diameter), m.
    ellipticity : float
        ``e``.
    orientation_rad : float
    harmonics : tuple of (k, A_k m, p_k rad)
    """

    radius_m: float
    ellipticity: float = 0.0
    orientation_rad: float = 0.0
    harmonics: tuple[tuple[int, float, float], ...] = ()

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PrintShape:
        """From :func:`pipeline.sim.optics.draw_print`'s dictionary."""
        return cls(
            radius_m=float(d["radius_m"]),
            ellipticity=float(d["ellipticity"]),
            orientation_rad=float(d["orientation_rad"]),
            harmonics=tuple((int(k), float(a), float(p)) for k, a, p in d["harmonics"]),
        )

    @property
    def is_circle(self) -> bool:
        return self.ellipticity == 0.0 and not self.harmonics

    def radius_at(self, phi: ArrayLike) -> F64:
        """Boundary radius ``r(phi)`` (m) at polar angles ``phi`` (rad, any shape)."""
        ph = np.asarray(phi, dtype=float)
        a = self.radius_m * (1.0 + self.ellipticity)
        b = self.radius_m * (1.0 - self.ellipticity)
        psi = ph - self.orientation_rad
        r = a * b / np.sqrt((b * np.cos(psi)) ** 2 + (a * np.sin(psi)) ** 2)
        for k, amp, p in self.harmonics:
            r = r + amp * np.cos(k * ph + p)
        out: F64 = np.asarray(r, dtype=float)
        return out

    def max_radius(self) -> float:
        """An upper bound of ``r(phi)`` (m)."""
        return self.radius_m * (1.0 + abs(self.ellipticity)) + sum(
            abs(a) for _, a, _ in self.harmonics
        )

    def band_factor(self) -> float:
        """Widening of the edge band for a boundary not normal to the radius (slope bound)."""
        slope = 2.0 * abs(self.ellipticity) + sum(k * abs(a) for k, a, _ in self.harmonics) / max(
            self.radius_m, 1e-12
        )
        return 1.25 + slope


def fit_ellipse(points: ArrayLike) -> tuple[float, float, float, float, float]:
    """Least-squares conic fit to points on a closed contour.

    Fits ``A x^2 + B x y + C y^2 + D x + E y + F = 0`` (smallest right singular
    vector of the design matrix, points centred and scaled first for
    conditioning), then converts to centre, full axes and long-axis angle.

    Parameters
    ----------
    points : (N, 2), N >= 5

    Returns
    -------
    u, v, long_axis, short_axis, angle_rad
        Centre, full axis lengths, angle of the long axis from ``+u`` towards
        ``+v`` in ``(-pi/2, pi/2]``.
    """
    p = np.asarray(points, dtype=float)
    m = p.mean(axis=0)
    sc = float(np.sqrt(np.mean(np.sum((p - m) ** 2, axis=1))))
    q = (p - m) / sc
    x, y = q[:, 0], q[:, 1]
    Dm = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    _, _, Vt = np.linalg.svd(Dm, full_matrices=False)
    A, B, C, D, E, F = Vt[-1]
    M2 = np.array([[2 * A, B], [B, 2 * C]])
    x0, y0 = np.linalg.solve(M2, [-D, -E])
    F0 = F + 0.5 * (D * x0 + E * y0)
    Mq = np.array([[A, B / 2], [B / 2, C]])
    lam, vec = np.linalg.eigh(Mq)
    if F0 > 0:
        lam, F0 = -lam, -F0
    axes = np.sqrt(-F0 / lam)  # semi-axes for eigenvalues in ascending order
    # ascending lam -> largest axis first only if both positive
    i_long = int(np.argmax(axes))
    i_short = 1 - i_long
    d = vec[:, i_long]
    ang = float(np.arctan2(d[1], d[0]))
    if ang <= -np.pi / 2:
        ang += np.pi
    elif ang > np.pi / 2:
        ang -= np.pi
    u = float(m[0] + sc * x0)
    v = float(m[1] + sc * y0)
    return u, v, float(2 * sc * axes[i_long]), float(2 * sc * axes[i_short]), ang


def projected_contour(
    camera: CameraModel,
    T_camera_target: ArrayLike,
    diameter_m: float,
    n: int = 720,
    shape: PrintShape | None = None,
) -> F64:
    """Pixels ``(n, 2)`` of ``n`` points of the target circle (or printed ``shape``)
    through the camera model."""
    T = np.asarray(T_camera_target, dtype=float)
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = 0.5 * diameter_m if shape is None else shape.radius_at(a)
    pts = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], axis=-1)
    return camera.project(pts @ T[:3, :3].T + T[:3, 3])


def projected_ellipse(
    camera: CameraModel,
    T_camera_target: ArrayLike,
    diameter_m: float,
    n: int = 720,
    shape: PrintShape | None = None,
) -> tuple[float, float, float, float, float]:
    """The true image ellipse of the target: fit to its exactly projected contour.

    Parameters
    ----------
    camera : CameraModel
    T_camera_target : (4, 4)
    diameter_m : float
    n : int
        Number of circle points projected.
    shape : PrintShape, optional
        The printed boundary ``r(phi)`` instead of the circle of ``diameter_m``
        (points at ``n`` equally spaced polar angles).

    Returns
    -------
    u, v, long_axis_px, short_axis_px, angle_rad
        See :func:`fit_ellipse`; the long axis is the full length ``s``.
    """
    return fit_ellipse(projected_contour(camera, T_camera_target, diameter_m, n, shape))
