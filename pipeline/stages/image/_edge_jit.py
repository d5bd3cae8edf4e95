"""Compiled (numba) residual and Jacobian of the edge model (R1)-(R2), one pass per term.

The same quantities as :class:`pipeline.stages.image.response_fit.EdgeFit` (its
docstring holds the model and the variable-projection Jacobian (J)), computed
in three loops over the profile's pixels instead of a few dozen NumPy calls and
a QR factorisation per evaluation: the projection on ``A``'s six columns goes
through the 6 x 6 Gram matrix ``G = A^T A`` (Cholesky), with the offsets
``du, dv`` divided by their RMS first (a column scale changes neither the
projector ``P = A G^-1 A^T``, nor ``r``, nor ``J``; it keeps ``G``'s condition
number near that of the levels, ~1e2)::

    c = G^-1 A^T y,   r = A c - y
    J_k = A_k c - A G^-1 (A^T A_k c) - A G^-1 (A_k^T r)                   (J)

``tests/test_response_fit.py`` holds both to the NumPy reference (1e-9) and
(J) to finite differences. The NumPy path stays the reference, and the one
the edge-harmonics fit uses.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_SQRT2 = math.sqrt(2.0)


@njit(cache=True)
def _chol_solve(L, b):  # type: ignore[no-untyped-def]
    """``x`` with ``L L^T x = b`` (``L`` lower triangular 6 x 6, ``b`` (6,))."""
    n = 6
    z = np.empty(n)
    for i in range(n):
        s = b[i]
        for j in range(i):
            s -= L[i, j] * z[j]
        z[i] = s / L[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = z[i]
        for j in range(i + 1, n):
            s -= L[j, i] * x[j]
        x[i] = s / L[i, i]
    return x


@njit(cache=True)
def edge_residual_jacobian(d, du, dv, y, w, x, min_sigma, r, J):  # type: ignore[no-untyped-def]
    """Fill ``r`` (N,) and ``J`` (N, len(x)) of model (R1)-(R2) at ``x = (delta, sigma, b...)``.

    ``d, du, dv, y, w`` as :class:`~pipeline.stages.image.response_fit.EdgeFit` (``y = w E``);
    ``len(x) - 2`` (0, 1 or 2) odd shape terms. Returns False when the Gram matrix is
    singular (the caller then takes the NumPy path).

    With ``e = (1, u, v)`` (the offsets scaled), ``p = w (1 - F)`` and ``q = w F`` a
    row of ``A`` is ``(p e, q e)``, so ``G`` is three 3 x 3 blocks of ``e e^T``
    weighted by ``p^2, p q, q^2``; and since ``A_k = w F_k (-e, e)``, the two
    right-hand sides of (J) sum to ``(sum alpha_k e, sum beta_k e)`` with
    ``alpha_k = w F_k (p g - r)``, ``beta_k = w F_k (q g + r)``, ``g = (c_q - c_p) . e``.
    """
    n = d.shape[0]
    nb = x.shape[0] - 2
    nk = 2 + nb
    b3 = x[2] if nb > 0 else 0.0
    b5 = x[3] if nb > 1 else 0.0
    s = abs(x[1])
    clipped = s < min_sigma
    if clipped:
        s = min_sigma
    sgn = 1.0 if x[1] > 0.0 else (-1.0 if x[1] < 0.0 else 0.0)
    su = 0.0
    sv = 0.0
    for i in range(n):
        su += du[i] * du[i]
        sv += dv[i] * dv[i]
    su = 1.0 / math.sqrt(su / n) if su > 0.0 else 1.0
    sv = 1.0 / math.sqrt(sv / n) if sv > 0.0 else 1.0
    F = np.empty(n)
    dFdt = np.empty(n)
    he3 = np.empty(n)
    he5 = np.empty(n)
    t = np.empty(n)
    # the Gram blocks: sum of weight * (1, u, v, uu, uv, vv) for weights p^2, p q, q^2
    gpp = np.zeros(6)
    gpq = np.zeros(6)
    gqq = np.zeros(6)
    h = np.zeros(6)
    for i in range(n):
        ti = (d[i] - x[0]) / s
        t[i] = ti
        t2 = ti * ti
        ph = math.exp(-0.5 * t2) * _INV_SQRT_2PI
        Fi = 0.5 * math.erfc(-ti / _SQRT2)
        dfi = ph
        h3 = (ti * t2 - 3.0 * ti) * ph
        h5 = (ti * t2 * t2 - 10.0 * ti * t2 + 15.0 * ti) * ph
        if nb > 0:
            Fi += b3 * h3
            dfi -= b3 * (t2 * t2 - 6.0 * t2 + 3.0) * ph
        if nb > 1:
            Fi += b5 * h5
            dfi -= b5 * (t2 * t2 * t2 - 15.0 * t2 * t2 + 45.0 * t2 - 15.0) * ph
        F[i] = Fi
        dFdt[i] = dfi
        he3[i] = h3
        he5[i] = h5
        p = w[i] * (1.0 - Fi)
        q = w[i] * Fi
        u = du[i] * su
        v = dv[i] * sv
        uu = u * u
        uv = u * v
        vv = v * v
        pp = p * p
        pq = p * q
        qq = q * q
        gpp[0] += pp
        gpp[1] += pp * u
        gpp[2] += pp * v
        gpp[3] += pp * uu
        gpp[4] += pp * uv
        gpp[5] += pp * vv
        gpq[0] += pq
        gpq[1] += pq * u
        gpq[2] += pq * v
        gpq[3] += pq * uu
        gpq[4] += pq * uv
        gpq[5] += pq * vv
        gqq[0] += qq
        gqq[1] += qq * u
        gqq[2] += qq * v
        gqq[3] += qq * uu
        gqq[4] += qq * uv
        gqq[5] += qq * vv
        py = p * y[i]
        qy = q * y[i]
        h[0] += py
        h[1] += py * u
        h[2] += py * v
        h[3] += qy
        h[4] += qy * u
        h[5] += qy * v
    G = np.empty((6, 6))
    # e e^T entries (row, col) -> index into (1, u, v, uu, uv, vv)
    idx = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
    for j in range(3):
        for k in range(3):
            m = idx[j, k]
            G[j, k] = gpp[m]
            G[j, 3 + k] = gpq[m]
            G[3 + j, k] = gpq[m]
            G[3 + j, 3 + k] = gqq[m]
    L = np.zeros((6, 6))
    for j in range(6):
        sjj = G[j, j]
        for k in range(j):
            sjj -= L[j, k] * L[j, k]
        if not sjj > 0.0:
            return False
        L[j, j] = math.sqrt(sjj)
        for i in range(j + 1, 6):
            sij = G[i, j]
            for k in range(j):
                sij -= L[i, k] * L[j, k]
            L[i, j] = sij / L[j, j]
    c = _chol_solve(L, h)
    c0, c1, c2, c3, c4, c5 = c[0], c[1], c[2], c[3], c[4], c[5]
    d0, d1, d2 = c3 - c0, c4 - c1, c5 - c2
    RHS = np.zeros((6, nk))
    dF = np.empty(nk)
    for i in range(n):
        Fi = F[i]
        wi = w[i]
        p = wi * (1.0 - Fi)
        q = wi * Fi
        u = du[i] * su
        v = dv[i] * sv
        ri = p * (c0 + c1 * u + c2 * v) + q * (c3 + c4 * u + c5 * v) - y[i]
        r[i] = ri
        g = d0 + d1 * u + d2 * v
        dF[0] = -dFdt[i] / s
        dF[1] = 0.0 if clipped else -dFdt[i] * t[i] / s * sgn
        if nb > 0:
            dF[2] = he3[i]
        if nb > 1:
            dF[3] = he5[i]
        pg = p * g - ri
        qg = q * g + ri
        for k in range(nk):
            wf = wi * dF[k]
            J[i, k] = wf * g  # A_k c, the projections taken off below
            al = wf * pg
            be = wf * qg
            RHS[0, k] += al
            RHS[1, k] += al * u
            RHS[2, k] += al * v
            RHS[3, k] += be
            RHS[4, k] += be * u
            RHS[5, k] += be * v
    P = np.empty((6, nk))
    for k in range(nk):
        P[:, k] = _chol_solve(L, RHS[:, k].copy())
    for i in range(n):
        Fi = F[i]
        p = w[i] * (1.0 - Fi)
        q = w[i] * Fi
        u = du[i] * su
        v = dv[i] * sv
        for k in range(nk):
            J[i, k] -= p * (P[0, k] + P[1, k] * u + P[2, k] * v) + q * (
                P[3, k] + P[4, k] * u + P[5, k] * v
            )
    return True
