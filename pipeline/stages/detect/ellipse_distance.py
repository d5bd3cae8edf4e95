"""The signed distance of image points to an ellipse, shared by detection and saturation."""

from __future__ import annotations

import numpy as np


def approx_distance(pts: np.ndarray, p: tuple[float, float, float, float, float]) -> np.ndarray:
    """First-order signed distance of points to an ellipse, ``(rho - 1) / |grad rho|``.

    With ``(x, y)`` the point in the ellipse's axes scaled by ``(a, b)``,
    ``rho = sqrt(x^2 + y^2)`` is 1 on the ellipse; dividing ``rho - 1`` by the
    gradient's norm ``|grad rho| = sqrt((x/a)^2 + (y/b)^2) / rho`` gives the
    distance to first order (Sampson's approximation for a conic).

    Parameters
    ----------
    pts : (N, 2) image points ``(u, v)``, px
    p : ellipse ``(u0, v0, a, b, theta)``: centre, semi-axes (px), angle of ``a`` (rad)

    Returns
    -------
    (N,) signed distances, px: negative inside
    """
    u0, v0, a, b, th = p
    c, s = np.cos(th), np.sin(th)
    du = pts[:, 0] - u0
    dv = pts[:, 1] - v0
    x = (c * du + s * dv) / a
    y = (-s * du + c * dv) / b
    rho = np.sqrt(x * x + y * y) + 1e-12
    g = np.sqrt((x / a) ** 2 + (y / b) ** 2) / rho
    return (rho - 1.0) / g
