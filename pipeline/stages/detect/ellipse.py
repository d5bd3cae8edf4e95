"""Conic and ellipse geometry of the detector (step 4 of :mod:`pipeline.stages.detect.detector`).

An algebraic conic fit on normalised coordinates (:func:`fit_conic`), its
centre, semi-axes and angle (:func:`conic_to_params`), the signed orthogonal
distance of points to an ellipse with the foot point's parameter angle and
curvature (:func:`ellipse_foot`), the outward normals (:func:`ellipse_normals`),
and Gauss-Newton on the geometric distances (:func:`refine_geometric`).
An ellipse is ``(u, v, a, b, theta)``: centre (px), semi-axes ``a >= b`` (px),
long-axis angle from ``+u`` towards ``+v``.
"""

from __future__ import annotations

import numpy as np


def fit_conic(pts: np.ndarray) -> np.ndarray | None:
    """Algebraic conic fit ``A x^2 + B xy + C y^2 + D x + E y + F = 0``.

    Minimises ``sum (conic(x_i))^2`` with ``|coefficients| = 1``: the smallest
    right singular vector of the design matrix (here the eigenvector of its
    scatter matrix), on centred, scaled points (Hartley-style normalisation),
    mapped back to pixel coordinates.

    Parameters
    ----------
    pts : (N, 2), N >= 5

    Returns
    -------
    (6,) conic coefficients in pixel coordinates, or None if degenerate.
    """
    if pts.shape[0] < 6:
        return None
    m = pts.mean(axis=0)
    q = pts - m
    sc = float(np.sqrt(np.mean(np.sum(q * q, axis=1))))
    if not sc > 0:
        return None
    x = q[:, 0] / sc
    y = q[:, 1] / sc
    D = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    # smallest eigenvector of the scatter matrix = smallest right singular vector
    _, V = np.linalg.eigh(D.T @ D)
    a, b, c, d, e, f = V[:, 0]
    # undo scaling then translation: x = (X - mx)/sc
    a, b, c, d, e = a / sc**2, b / sc**2, c / sc**2, d / sc, e / sc
    mx, my = m
    A, B, C = a, b, c
    Dn = d - 2 * a * mx - b * my
    En = e - 2 * c * my - b * mx
    Fn = f + a * mx * mx + b * mx * my + c * my * my - d * mx - e * my
    return np.array([A, B, C, Dn, En, Fn])


def conic_to_params(k: np.ndarray) -> tuple[float, float, float, float, float] | None:
    """Conic -> ``(u, v, a, b, theta)``: centre, semi-axes ``a >= b``, long-axis angle.

    ``theta`` is measured from ``+u`` towards ``+v``, in ``(-pi/2, pi/2]``.
    Returns None when the conic is not a real ellipse.
    """
    A, B, C, D, E, F = k
    det = 4 * A * C - B * B
    if det <= 0:
        return None
    # centre: gradient zero, [[2A, B], [B, 2C]] (x0, y0) = (-D, -E)
    x0 = (B * E - 2 * C * D) / det
    y0 = (B * D - 2 * A * E) / det
    F0 = F + 0.5 * (D * x0 + E * y0)
    # eigen-decomposition of [[A, B/2], [B/2, C]] in closed form
    half_diff = 0.5 * (A - C)
    rad = float(np.hypot(half_diff, 0.5 * B))
    mean_ac = 0.5 * (A + C)
    lam = np.array([mean_ac - rad, mean_ac + rad])
    phi = 0.5 * float(np.arctan2(B, A - C))  # direction of the larger eigenvalue
    vec = np.array([[-np.sin(phi), np.cos(phi)], [np.cos(phi), np.sin(phi)]])
    if F0 > 0:
        lam, F0 = -lam, -F0
    if np.any(lam <= 0) or F0 >= 0:
        return None
    ax = np.sqrt(-F0 / lam)
    i = int(np.argmax(ax))
    d = vec[:, i]
    th = float(np.arctan2(d[1], d[0]))
    if th <= -np.pi / 2:
        th += np.pi
    elif th > np.pi / 2:
        th -= np.pi
    return float(x0), float(y0), float(ax[i]), float(ax[1 - i]), th


def ellipse_foot(
    pts: np.ndarray, p: tuple[float, float, float, float, float], newton: int = 4
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed geometric distance of points to an ellipse, the foot angle and curvature.

    Uses a few Newton steps on the parameter angle ``t`` of the closest point
    ``(a cos t, b sin t)`` in the ellipse frame.

    Returns
    -------
    dist : (N,) signed distance, positive outside
    t : (N,) parameter angle of the foot point
    kappa : (N,) curvature of the ellipse at the foot point, 1/px
    """
    u0, v0, a, b, th = p
    c, s = np.cos(th), np.sin(th)
    du = pts[:, 0] - u0
    dv = pts[:, 1] - v0
    x = c * du + s * dv
    y = -s * du + c * dv
    t = np.arctan2(a * y, b * x)
    for _ in range(newton):
        ct, st = np.cos(t), np.sin(t)
        # f(t) = (a^2 - b^2) ct st - x a st + y b ct = 0
        f = (a * a - b * b) * ct * st - x * a * st + y * b * ct
        fp = (a * a - b * b) * (ct * ct - st * st) - x * a * ct - y * b * st
        t = t - f / np.where(np.abs(fp) > 1e-12, fp, 1e-12)
    ct, st = np.cos(t), np.sin(t)
    ex, ey = a * ct, b * st
    d = np.hypot(x - ex, y - ey)
    inside = (x / a) ** 2 + (y / b) ** 2 < 1.0
    d = np.where(inside, -d, d)
    kappa = a * b / np.power(a * a * st * st + b * b * ct * ct, 1.5)
    return d, t, kappa


def ellipse_normals(p: tuple[float, float, float, float, float], t: np.ndarray) -> np.ndarray:
    """Outward unit normals ``(N, 2)`` in image coordinates at parameter angles ``t``."""
    _, _, a, b, th = p
    nx = b * np.cos(t)
    ny = a * np.sin(t)
    nn = np.hypot(nx, ny)
    nx, ny = nx / nn, ny / nn
    c, s = np.cos(th), np.sin(th)
    return np.stack([c * nx - s * ny, s * nx + c * ny], axis=1)


def refine_geometric(
    pts: np.ndarray, p: tuple[float, float, float, float, float], iterations: int = 3
) -> tuple[tuple[float, float, float, float, float], np.ndarray]:
    """Gauss-Newton on the orthogonal distances of ``pts`` to the ellipse ``p``.

    Parameters ``(u, v, a, b, theta)``; the distance derivatives are those of
    the foot point (the foot moves along the contour, so only the normal
    component counts): with ``d = n . (p - c - R e(t))``, ``dd/dc = -n``,
    ``dd/da = -n . R (cos t, 0)``, ``dd/db = -n . R (0, sin t)``,
    ``dd/dtheta = -n . R' (a cos t, b sin t)``.

    Returns the refined parameters and the final residuals ``(N,)``.
    """
    q = np.array(p, dtype=float)
    d = np.zeros(len(pts))
    for _ in range(iterations):
        pp = (q[0], q[1], q[2], q[3], q[4])
        d, t, _ = ellipse_foot(pts, pp)
        n = ellipse_normals(pp, t)
        c, s = np.cos(q[4]), np.sin(q[4])
        ct, st = np.cos(t), np.sin(t)
        Ja = n[:, 0] * c * ct + n[:, 1] * s * ct
        Jb = -n[:, 0] * s * st + n[:, 1] * c * st
        ex, ey = q[2] * ct, q[3] * st
        # d(R e)/dtheta = (-s ex - c ey, c ex - s ey)
        Jt = n[:, 0] * (-s * ex - c * ey) + n[:, 1] * (c * ex - s * ey)
        J = -np.stack([n[:, 0], n[:, 1], Ja, Jb, Jt], axis=1)
        step, *_ = np.linalg.lstsq(J, -d, rcond=None)
        q = q + step
        if np.max(np.abs(step[:4])) < 1e-7:
            break
    if q[3] > q[2]:
        q[2], q[3] = q[3], q[2]
        q[4] += np.pi / 2
    q[4] = (q[4] + np.pi / 2) % np.pi - np.pi / 2
    pp = (q[0], q[1], q[2], q[3], q[4])
    d, _, _ = ellipse_foot(pts, pp)
    return pp, d
