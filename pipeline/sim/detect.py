"""The simulated controller's own target detection (what a real touch-up controller runs).

Deliberately independent of the renderer's truth: it sees only the ``uint8``
image. A threshold halfway between the darkest
pixels and the median, connected blobs (OpenCV contours), the most
plausible round blob (largest, or nearest an expected position), then a
sub-pixel estimate from grey-level moments inside a slightly dilated blob
mask with locally estimated target and plate levels:

    w = (g_plate - I) / (g_plate - g_target)   (not clipped: noise averages out)
    (u, v) = sum(w x) / sum(w)
    A = sum(w)  (blur conserves it: the area inside the half-level contour)
    s = 2 a,  a = sqrt(A / pi * sqrt(lambda_1 / lambda_2))

with ``lambda_1 >= lambda_2`` the eigenvalues of the weighted covariance (their
ratio is the squared axis ratio; blur biases it only to second order).
"""

from __future__ import annotations

import cv2
import numpy as np


def detect_target(
    img: np.ndarray,
    polarity: str = "dark_on_light",
    *,
    expected_uv: tuple[float, float] | None = None,
    min_area_px: float = 30.0,
    border_px: int = 2,
    method: str = "moments",
) -> tuple[float, float, float] | None:
    """Find the circular target and return ``(u, v, s)`` (centre, full long axis) or None.

    Parameters
    ----------
    img : (H, W) uint8
    polarity : ``dark_on_light`` or ``light_on_dark``
    expected_uv : optional
        Prefer the blob nearest this pixel (else the largest round blob).
    min_area_px : float
        Smaller blobs are ignored.
    border_px : int
        Blobs touching this margin are rejected (cut by the border).
    method : ``moments`` (default) or ``binary``
        ``binary`` is the simpler controller many cells run: centre and axes from the
        moments of the thresholded blob's contour polygon (one global threshold, pixel
        resolution), ``s = 2 sqrt(A / pi) (lambda_1 / lambda_2)^(1/4)``. Under uneven light
        its global threshold is not the local halfway level, so it stops a touch-up a few
        tenths of a pixel off the target (scenario ``[touchup] controller``).
    """
    g = img if polarity == "dark_on_light" else (255 - img)
    lo, mid = np.percentile(g[::2, ::2], [0.05, 50.0])
    if mid - lo < 40.0:
        return None
    _, mask = cv2.threshold(g, 0.5 * (lo + mid), 255, cv2.THRESH_BINARY_INV)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    H, W = g.shape
    best = None
    best_key = np.inf
    for c in contours:
        area = cv2.contourArea(c)
        if area < min_area_px:
            continue
        x, y, w, h = cv2.boundingRect(c)
        if x < border_px or y < border_px or x + w > W - border_px or y + h > H - border_px:
            continue
        per = cv2.arcLength(c, True)
        if per <= 0 or 4 * np.pi * area / per**2 < 0.55:
            continue
        m = cv2.moments(c)
        cu, cv = m["m10"] / m["m00"], m["m01"] / m["m00"]
        if expected_uv is not None:
            key = float(np.hypot(cu - expected_uv[0], cv - expected_uv[1]))
        else:
            key = -float(area)
        if key < best_key:
            best_key, best = key, c
    if best is None:
        return None
    if method == "binary":
        m = cv2.moments(best)
        if m["m00"] <= 0:
            return None
        mu = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
        lam_b = np.linalg.eigvalsh(mu)
        if lam_b[0] <= 0:
            return None
        a_b = np.sqrt(m["m00"] / np.pi * np.sqrt(lam_b[1] / lam_b[0]))
        return float(m["m10"] / m["m00"]), float(m["m01"] / m["m00"]), float(2 * a_b)
    x, y, w, h = cv2.boundingRect(best)
    pad = 10
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + w + pad, W), min(y + h + pad, H)
    blob = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.drawContours(blob, [best], -1, 255, thickness=cv2.FILLED, offset=(-x0, -y0))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    inner = cv2.dilate(blob, k, iterations=3) > 0
    outer = (cv2.dilate(blob, k, iterations=6) > 0) & ~inner
    core = cv2.erode(blob, k, iterations=3) > 0
    patch = g[y0:y1, x0:x1].astype(float)
    if not np.any(outer):
        return None
    g_plate = float(np.median(patch[outer]))
    g_target = float(np.median(patch[core])) if np.count_nonzero(core) >= 5 else float(patch.min())
    if g_plate - g_target < 10:
        return None
    wgt = np.where(inner, (g_plate - patch) / (g_plate - g_target), 0.0)
    A = float(wgt.sum())
    if A <= 0:
        return None
    vv, uu = np.mgrid[y0:y1, x0:x1].astype(float)
    cu = float((wgt * uu).sum() / A)
    cv = float((wgt * vv).sum() / A)
    du, dv = uu - cu, vv - cv
    cuu = float((wgt * du * du).sum() / A)
    cvv = float((wgt * dv * dv).sum() / A)
    cuv = float((wgt * du * dv).sum() / A)
    lam = np.linalg.eigvalsh(np.array([[cuu, cuv], [cuv, cvv]]))
    if lam[0] <= 0:
        return None
    a = np.sqrt(A / np.pi * np.sqrt(lam[1] / lam[0]))
    return cu, cv, float(2 * a)
