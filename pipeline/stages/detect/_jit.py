"""Compiled (numba) fine stage of :func:`pipeline.stages.detect.detector.detect_target`.

The same steps as the NumPy path in :mod:`pipeline.stages.detect.detector` and its parts
(:mod:`~pipeline.stages.detect.edges`, :mod:`~pipeline.stages.detect.ellipse`: level
planes, halfway crossings, conic fits, foot points, crossing selection,
edge width, interpolation-phase and blur-curvature corrections), written as
loops and compiled once (``cache=True``), so one image costs a few hundred
microseconds instead of a few hundred small NumPy calls. The NumPy path stays
the reference; tests check that both agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_SQRT2 = math.sqrt(2.0)


@njit(cache=True, nogil=True)
def _phi(x: float) -> float:
    return 0.5 * math.erfc(-x / _SQRT2)


@njit(cache=True, nogil=True)
def _noise_bias(mu: float, eps: float) -> float:
    """``E[c (1 - c)] - mu (1 - mu)``, ``c = clip(mu + eps Z, 0, 1)`` (detect.noise_bias_pq)."""
    if eps <= 0.0:
        return 0.0
    a = -mu / eps
    b = (1.0 - mu) / eps
    k = 1.0 / math.sqrt(2.0 * math.pi)
    # beyond 9 noise sigmas the density (< 1e-18) and the normal tail (< 1e-19)
    # are below the rounding of the other terms (~1e-17): skip those calls
    if a < -9.0:
        pa = 0.0
        phi_a = 0.0
    else:
        pa = k * math.exp(-0.5 * a * a)
        phi_a = _phi(a)
    if b > 9.0:
        pb = 0.0
        phi_b = 1.0
    else:
        pb = k * math.exp(-0.5 * b * b)
        phi_b = _phi(b)
    P = phi_b - phi_a
    m1 = mu * P + eps * (pa - pb)
    m2 = mu * mu * P + 2.0 * mu * eps * (pa - pb) + eps * eps * (P + a * pa - b * pb)
    return m1 - m2 - mu * (1.0 - mu)


@njit(cache=True, nogil=True)
def _moments(roi, core, outer, u0, v0):  # type: ignore[no-untyped-def]
    """Sums over the core (row 0) and outer (row 1) pixels, one pass over the window.

    Columns: ``n, du, dv, du^2, du dv, dv^2, g, g du, g dv, q, du q, dv q, q^2, g q``
    with ``du, dv`` from the window centre and ``q = du^2 + dv^2``.
    """
    H, W = roi.shape
    uc = u0 + 0.5 * (W - 1)
    vc = v0 + 0.5 * (H - 1)
    M = np.zeros((2, 14))
    for y in range(H):
        dv = v0 + y - vc
        for x in range(W):
            if core[y, x]:
                r = 0
            elif outer[y, x]:
                r = 1
            else:
                continue
            du = u0 + x - uc
            g = roi[y, x]
            q = du * du + dv * dv
            M[r, 0] += 1.0
            M[r, 1] += du
            M[r, 2] += dv
            M[r, 3] += du * du
            M[r, 4] += du * dv
            M[r, 5] += dv * dv
            M[r, 6] += g
            M[r, 7] += g * du
            M[r, 8] += g * dv
            M[r, 9] += q
            M[r, 10] += du * q
            M[r, 11] += dv * q
            M[r, 12] += q * q
            M[r, 13] += g * q
    return M


@njit(cache=True, nogil=True)
def _plane3(m):  # type: ignore[no-untyped-def]
    """Plane ``g = c0 + c1 du + c2 dv`` from one row of :func:`_moments`; count."""
    A = np.empty((3, 3))
    A[0, 0] = m[0]
    A[0, 1] = m[1]
    A[0, 2] = m[2]
    A[1, 1] = m[3]
    A[1, 2] = m[4]
    A[2, 2] = m[5]
    A[1, 0] = A[0, 1]
    A[2, 0] = A[0, 2]
    A[2, 1] = A[1, 2]
    b = np.empty(3)
    b[0] = m[6]
    b[1] = m[7]
    b[2] = m[8]
    out = np.zeros(3)
    n = A[0, 0]
    if n < 6:
        if n > 0:
            out[0] = b[0] / n
        return out, n
    for i in range(3):
        A[i, i] += 1e-9
    out[:] = np.linalg.solve(A, b)
    return out, n


@njit(cache=True, nogil=True)
def _level_surfaces(roi, core, outer, u0, v0):  # type: ignore[no-untyped-def]
    """Target and plate level surfaces with one shared vignetting term (detect_edges.level_surfaces).

    The normal equations of both fits are assembled from the window's moment
    sums (:func:`_moments`, one pass), not pixel by pixel.

    Returns (GI, level_in, GO, level_out): (H, W) surfaces and their values at
    the window centre.
    """
    H, W = roi.shape
    uc = u0 + 0.5 * (W - 1)
    vc = v0 + 0.5 * (H - 1)
    M = _moments(roi, core, outer, u0, v0)
    a, n_a = _plane3(M[0])
    b, n_b = _plane3(M[1])
    lv_a = a[0]
    lv_b = b[0]
    k = 0.0
    if n_a >= 30 and n_b >= 30:
        # regressors: core (1, du, dv) in columns 0-2, outer (1, du, dv) in 3-5,
        # the shared vignetting term level * q in column 6
        A = np.zeros((7, 7))
        r = np.zeros(7)
        for reg in range(2):
            m = M[reg]
            o = 3 * reg
            lv = lv_a if reg == 0 else lv_b
            A[o, o] = m[0]
            A[o, o + 1] = m[1]
            A[o, o + 2] = m[2]
            A[o + 1, o + 1] = m[3]
            A[o + 1, o + 2] = m[4]
            A[o + 2, o + 2] = m[5]
            A[o, 6] = lv * m[9]
            A[o + 1, 6] = lv * m[10]
            A[o + 2, 6] = lv * m[11]
            A[6, 6] += lv * lv * m[12]
            r[o] = m[6]
            r[o + 1] = m[7]
            r[o + 2] = m[8]
            r[6] += lv * m[13]
        for i in range(7):
            for j in range(i):
                A[i, j] = A[j, i]
        for i in range(7):
            A[i, i] += 1e-9
        c = np.linalg.solve(A, r)
        a[:] = c[0:3]
        b[:] = c[3:6]
        k = c[6]
    GI = np.zeros((H, W))
    GO = np.zeros((H, W))
    for y in range(H):
        dv = v0 + y - vc
        for x in range(W):
            du = u0 + x - uc
            q = du * du + dv * dv
            GI[y, x] = a[0] + a[1] * du + a[2] * dv + k * lv_a * q
            GO[y, x] = b[0] + b[1] * du + b[2] * dv + k * lv_b * q
    return GI, a[0], GO, b[0]


@njit(cache=True, nogil=True)
def _fit(px, py, n):  # type: ignore[no-untyped-def]
    """Algebraic conic fit -> (ok, u, v, a, b, theta) (see detect.fit_conic / conic_to_params)."""
    if n < 6:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    mx = 0.0
    my = 0.0
    for i in range(n):
        mx += px[i]
        my += py[i]
    mx /= n
    my /= n
    ss = 0.0
    for i in range(n):
        ss += (px[i] - mx) ** 2 + (py[i] - my) ** 2
    sc = math.sqrt(ss / n)
    if not sc > 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    S = np.zeros((6, 6))
    row = np.zeros(6)
    for i in range(n):
        x = (px[i] - mx) / sc
        y = (py[i] - my) / sc
        row[0] = x * x
        row[1] = x * y
        row[2] = y * y
        row[3] = x
        row[4] = y
        row[5] = 1.0
        for r in range(6):
            for c in range(r, 6):
                S[r, c] += row[r] * row[c]
    for r in range(6):
        for c in range(r):
            S[r, c] = S[c, r]
    _, V = np.linalg.eigh(S)
    a = V[0, 0] / sc**2
    b = V[1, 0] / sc**2
    c = V[2, 0] / sc**2
    d = V[3, 0] / sc
    e = V[4, 0] / sc
    f = V[5, 0]
    A = a
    B = b
    C = c
    D = d - 2 * a * mx - b * my
    E = e - 2 * c * my - b * mx
    F = f + a * mx * mx + b * mx * my + c * my * my - d * mx - e * my
    det = 4 * A * C - B * B
    if det <= 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    x0 = (B * E - 2 * C * D) / det
    y0 = (B * D - 2 * A * E) / det
    F0 = F + 0.5 * (D * x0 + E * y0)
    rad = math.hypot(0.5 * (A - C), 0.5 * B)
    m = 0.5 * (A + C)
    l_small = m - rad  # eigenvalue of the long axis direction (if F0 < 0)
    l_big = m + rad
    phi = 0.5 * math.atan2(B, A - C)  # direction of l_big
    if F0 > 0:
        l_small, l_big, F0 = -l_small, -l_big, -F0
    if l_small <= 0 or l_big <= 0 or F0 >= 0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    ax_s = math.sqrt(-F0 / l_small)  # along (-sin phi, cos phi)
    ax_b = math.sqrt(-F0 / l_big)  # along (cos phi, sin phi)
    if ax_s >= ax_b:
        a_long, b_short = ax_s, ax_b
        th = math.atan2(math.cos(phi), -math.sin(phi))
    else:
        a_long, b_short = ax_b, ax_s
        th = phi
    if th <= -math.pi / 2:
        th += math.pi
    elif th > math.pi / 2:
        th -= math.pi
    return True, x0, y0, a_long, b_short, th


@njit(cache=True, nogil=True)
def _foot(x_, y_, u0, v0, a, b, th):  # type: ignore[no-untyped-def]
    """Signed distance (outside +), foot angle, curvature, outward normal (nx, ny)."""
    return _foot_cs(x_, y_, u0, v0, a, b, math.cos(th), math.sin(th))


@njit(cache=True, nogil=True)
def _foot_cs(x_, y_, u0, v0, a, b, c, s):  # type: ignore[no-untyped-def]
    """:func:`_foot` with ``c, s = cos(theta), sin(theta)`` given (hoisted out of loops)."""
    du = x_ - u0
    dv = y_ - v0
    x = c * du + s * dv
    y = -s * du + c * dv
    t = math.atan2(a * y, b * x)
    for _ in range(3):
        ct = math.cos(t)
        st = math.sin(t)
        f = (a * a - b * b) * ct * st - x * a * st + y * b * ct
        fp = (a * a - b * b) * (ct * ct - st * st) - x * a * ct - y * b * st
        if abs(fp) < 1e-12:
            fp = 1e-12
        t = t - f / fp
    ct = math.cos(t)
    st = math.sin(t)
    d = math.hypot(x - a * ct, y - b * st)
    if (x / a) ** 2 + (y / b) ** 2 < 1.0:
        d = -d
    kap = a * b / (a * a * st * st + b * b * ct * ct) ** 1.5
    nx = b * ct
    ny = a * st
    nn = math.hypot(nx, ny)
    nx /= nn
    ny /= nn
    return d, t, kap, c * nx - s * ny, s * nx + c * ny


@njit(cache=True, nogil=True)
def fine_stage(roi, core, outer, u0, v0, cont_x, cont_y, near_tol, correct, max_sigma, min_step):  # type: ignore[no-untyped-def]
    """Levels, crossings, fits and corrections on one window.

    Returns an array: ``[status, u, v, a, b, theta, res_rms, completeness, sigma,
    n_points, lvl_in, lvl_out]``; status 0 ok, 1 fit failed.
    """
    out = np.zeros(12)
    H, W = roi.shape
    GI, lvl_in, GO, lvl_out = _level_surfaces(roi, core, outer, u0, v0)
    out[10] = lvl_in
    out[11] = lvl_out
    out[0] = 1.0
    # halfway crossings along rows and columns: h = g - g_mid and the local
    # contrast |g_out - g_in|, computed once per pixel
    hh = np.empty((H, W))
    am = np.empty((H, W))
    for y in range(H):
        for x in range(W):
            gi0 = GI[y, x]
            go0 = GO[y, x]
            hh[y, x] = roi[y, x] - 0.5 * (gi0 + go0)
            am[y, x] = abs(go0 - gi0)
    cap = 2 * H * W
    px = np.empty(cap)
    py = np.empty(cap)
    isrow = np.empty(cap, dtype=np.bool_)
    n = 0
    for y in range(H):
        vv = v0 + y
        for x in range(W - 1):
            h0 = hh[y, x]
            h1 = hh[y, x + 1]
            if (h0 * h1 < 0 or (h0 == 0 and h1 != 0)) and abs(h1 - h0) > min_step * 0.5 * (
                am[y, x] + am[y, x + 1]
            ):
                px[n] = u0 + x + h0 / (h0 - h1)
                py[n] = vv
                isrow[n] = True
                n += 1
    for y in range(H - 1):
        vv = v0 + y
        for x in range(W):
            h0 = hh[y, x]
            h1 = hh[y + 1, x]
            if (h0 * h1 < 0 or (h0 == 0 and h1 != 0)) and abs(h1 - h0) > min_step * 0.5 * (
                am[y, x] + am[y + 1, x]
            ):
                px[n] = u0 + x
                py[n] = vv + h0 / (h0 - h1)
                isrow[n] = False
                n += 1
    if n < 8:
        return out
    # keep the crossings near the initial ellipse, fit
    has_init, iu, iv, ia, ib, it = _fit(cont_x, cont_y, len(cont_x))
    init = np.array([iu, iv, ia, ib, it])
    ok = False
    u_, v_, a_, b_, t_ = 0.0, 0.0, 0.0, 0.0, 0.0
    if has_init:
        qx = np.empty(n)
        qy = np.empty(n)
        m = 0
        c = math.cos(init[4])
        s = math.sin(init[4])
        for i in range(n):
            du = px[i] - init[0]
            dv = py[i] - init[1]
            xx = (c * du + s * dv) / init[2]
            yy = (-s * du + c * dv) / init[3]
            rho = math.sqrt(xx * xx + yy * yy) + 1e-12
            g = math.sqrt((xx / init[2]) ** 2 + (yy / init[3]) ** 2) / rho
            if abs((rho - 1.0) / g) < near_tol:
                qx[m] = px[i]
                qy[m] = py[i]
                m += 1
        if m >= 8:
            ok, u_, v_, a_, b_, t_ = _fit(qx, qy, m)
    if not ok:
        ok, u_, v_, a_, b_, t_ = _fit(px, py, n)
    if not ok:
        return out
    # selection by the normal, outliers by the distance
    d0 = np.empty(n)
    t0 = np.empty(n)
    k0 = np.empty(n)
    nx0 = np.empty(n)
    ny0 = np.empty(n)
    keep = np.zeros(n, dtype=np.bool_)
    sabs = 0.0
    nk = 0
    c_t = math.cos(t_)
    s_t = math.sin(t_)
    for i in range(n):
        d0[i], t0[i], k0[i], nx0[i], ny0[i] = _foot_cs(px[i], py[i], u_, v_, a_, b_, c_t, s_t)
        keep[i] = abs(nx0[i]) >= 0.5 if isrow[i] else abs(ny0[i]) >= 0.5
        if keep[i]:
            sabs += abs(d0[i])
            nk += 1
    scale_d = 1.25 * sabs / nk + 0.05 if nk > 0 else 1.0
    lim = max(4 * scale_d, 0.5)
    m = 0
    for i in range(n):
        if keep[i] and abs(d0[i]) < lim:
            px[m] = px[i]
            py[m] = py[i]
            isrow[m] = isrow[i]
            t0[m] = t0[i]
            k0[m] = k0[i]
            nx0[m] = nx0[i]
            ny0[m] = ny0[i]
            m += 1
    if m < 8:
        return out
    # completeness: 36 sectors of the parameter angle
    bins = np.zeros(36, dtype=np.bool_)
    for i in range(m):
        tt = t0[i] % (2 * math.pi)
        bins[int(tt / (2 * math.pi) * 36) % 36] = True
    completeness = 0.0
    for j in range(36):
        if bins[j]:
            completeness += 1.0
    completeness /= 36.0
    # edge width from the normalised profile within 3 px of the contour
    c = math.cos(t_)
    s = math.sin(t_)
    edge_sum = 0.0
    n_band = 0.0
    s1 = 0.0
    s2 = 0.0
    n_out = 0.0
    csum = 0.0
    band_d = np.empty(H * W)  # distances of the band pixels, in pixel order
    band_skip = 3.0 * (1.0 + 1e-6)
    for y in range(H):
        vv = v0 + y
        for x in range(W):
            uu = u0 + x
            gi = GI[y, x]
            go = GO[y, x]
            if outer[y, x]:
                r = roi[y, x] - go
                s1 += r
                s2 += r * r
                n_out += 1.0
            du = uu - u_
            dv = vv - v_
            xx = (c * du + s * dv) / a_
            yy = (-s * du + c * dv) / b_
            rho = math.sqrt(xx * xx + yy * yy) + 1e-12
            # |grad rho| <= 1 / b_, so |d| >= |rho - 1| b_: far pixels skip the rest
            if abs(rho - 1.0) * b_ > band_skip:
                continue
            g = math.sqrt((xx / a_) ** 2 + (yy / b_) ** 2) / rho
            dd = (rho - 1.0) / g
            if abs(dd) < 3.0:
                band_d[int(n_band)] = dd
                diff = go - gi
                if abs(diff) < 1e-9:
                    diff = 1e-9
                p = min(max((roi[y, x] - gi) / diff, 0.0), 1.0)
                edge_sum += p * (1.0 - p)
                n_band += 1.0
                csum += abs(diff)
    noise = math.sqrt(max(s2 / n_out - (s1 / n_out) ** 2, 0.0)) if n_out > 10 else 0.0
    contrast = csum / n_band if n_band > 0 else 1.0
    eps = noise / max(contrast, 1e-9)
    h = ((a_ - b_) / (a_ + b_)) ** 2
    perim = (
        math.pi * (a_ + b_) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h))) * max(completeness, 1e-3)
    )
    # remove the expected noise bias of each band pixel (detect.noise_bias_pq), two passes
    sigma = math.sqrt(math.pi) * max(edge_sum, 0.0) / perim
    for _pass in range(2):
        sg_b = max(sigma, 0.05)
        bias_sum = 0.0
        # beyond 7.5 edge widths the normalised level is within 4e-14 of 0 or 1
        # and so is the bias term of its value there (computed once): the sum
        # moves by < 1e-10 (sigma by < 1e-11 px)
        bias_hi = _noise_bias(1.0, eps)
        bias_lo = _noise_bias(0.0, eps)
        for i in range(int(n_band)):
            tb = band_d[i] / sg_b
            if tb > 7.5:
                bias_sum += bias_hi
            elif tb < -7.5:
                bias_sum += bias_lo
            else:
                bias_sum += _noise_bias(_phi(tb), eps)
        sigma = math.sqrt(math.pi) * max(edge_sum - bias_sum, 0.0) / perim
    if correct and sigma > 0:
        sg = min(sigma, max_sigma)
        for i in range(m):
            # interpolation phase (erf profile), then blur on the curved contour
            if isrow[i]:
                base = math.floor(px[i])
                t = px[i] - base
                nc = nx0[i]
            else:
                base = math.floor(py[i])
                t = py[i] - base
                nc = ny0[i]
            na = max(abs(nc), 0.3)
            # contour curvature: distance of a point delta along the row/column
            # is delta n + kappa delta^2 (1 - n^2) / 2 (detect_edges.unbias_crossings)
            q = 0.5 * k0[i] * max(1.0 - nc * nc, 0.0)
            if nc < 0.0:
                q = -q
            cc = t
            for _ in range(4):
                lo = _phi((-cc * na + q * cc * cc) / sg)
                hi = _phi(((1.0 - cc) * na + q * (1.0 - cc) * (1.0 - cc)) / sg)
                den = max(hi - lo, 1e-12)
                tc = (0.5 - lo) / den
                cc = min(max(cc + (t - tc), 0.0), 1.0)
            if isrow[i]:
                px[i] = base + cc
            else:
                py[i] = base + cc
            shift = 0.5 * sg * sg * k0[i]
            px[i] += nx0[i] * shift
            py[i] += ny0[i] * shift
    ok, u_, v_, a_, b_, t_ = _fit(px, py, m)
    if not ok:
        return out
    rs = 0.0
    c_t = math.cos(t_)
    s_t = math.sin(t_)
    for i in range(m):
        d, _, _, _, _ = _foot_cs(px[i], py[i], u_, v_, a_, b_, c_t, s_t)
        rs += d * d
    out[0] = 0.0
    out[1] = u_
    out[2] = v_
    out[3] = a_
    out[4] = b_
    out[5] = t_
    out[6] = math.sqrt(rs / m)
    out[7] = completeness
    out[8] = sigma
    out[9] = m
    return out


@njit(cache=True, nogil=True)
def coarse_uint8(img, k):  # type: ignore[no-untyped-def]
    """Subsampled copy and levels of a uint8 image for the coarse blob search.

    ``small = img[k//2 : Hs k : k, k//2 : Ws k : k]`` (``Hs, Ws = H // k, W // k``),
    the plate level ``bg`` = the ``(n // 2)``-th smallest of ``small[::2, ::2]``
    (``n`` its size; the same order statistic as ``np.partition``, here from a
    256-bin histogram), and the extremes of ``small``.

    Returns (small (Hs, Ws) uint8, bg, lo, hi).
    """
    H, W = img.shape
    Hs = H // k
    Ws = W // k
    o = k // 2
    small = np.empty((Hs, Ws), dtype=np.uint8)
    hist = np.zeros(256, dtype=np.int64)
    lo = 255
    hi = 0
    for y in range(Hs):
        yy = o + y * k
        for x in range(Ws):
            g = img[yy, o + x * k]
            small[y, x] = g
            if g < lo:
                lo = g
            if g > hi:
                hi = g
            if y % 2 == 0 and x % 2 == 0:
                hist[g] += 1
    n = ((Hs + 1) // 2) * ((Ws + 1) // 2)
    half = n // 2
    cum = 0
    bg = 0
    for v in range(256):
        cum += hist[v]
        if cum > half:
            bg = v
            break
    return small, float(bg), float(lo), float(hi)
