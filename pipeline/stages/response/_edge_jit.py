"""Compiled (numba) residual and Jacobian of the edge model (R1)-(R2), one pass per term.

The same quantities as :class:`pipeline.stages.response.edge_fit.EdgeFit` (its
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
def _profile_and_gram(d, du, dv, y, w, x, s, su, sv, F, dFdt, he3, he5, t):  # type: ignore[no-untyped-def]
    """Pass 1: ``F``, ``dF/dt``, ``He3 phi``, ``He5 phi``, ``t`` per pixel; ``G`` and ``A^T y``."""
    n = d.shape[0]
    nb = x.shape[0] - 2
    b3 = x[2] if nb > 0 else 0.0
    b5 = x[3] if nb > 1 else 0.0
    # the Gram blocks: sum of weight * (1, u, v, uu, uv, vv) for weights p^2, p q, q^2
    g = np.zeros((3, 6))
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
        e = (1.0, u, v, u * u, u * v, v * v)
        pp = p * p
        pq = p * q
        qq = q * q
        for m in range(6):
            g[0, m] += pp * e[m]
            g[1, m] += pq * e[m]
            g[2, m] += qq * e[m]
        py = p * y[i]
        qy = q * y[i]
        h[0] += py
        h[1] += py * u
        h[2] += py * v
        h[3] += qy
        h[4] += qy * u
        h[5] += qy * v
    G = np.empty((6, 6))
    idx = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])  # e e^T (row, col) -> (1, u, v, ...)
    for j in range(3):
        for k in range(3):
            m = idx[j, k]
            G[j, k] = g[0, m]
            G[j, 3 + k] = g[1, m]
            G[3 + j, k] = g[1, m]
            G[3 + j, 3 + k] = g[2, m]
    return G, h


@njit(cache=True)
def _cholesky(G):  # type: ignore[no-untyped-def]
    """Lower ``L`` with ``L L^T = G`` (6 x 6), or an empty array when ``G`` is not positive."""
    L = np.zeros((6, 6))
    for j in range(6):
        sjj = G[j, j]
        for k in range(j):
            sjj -= L[j, k] * L[j, k]
        if not sjj > 0.0:
            return np.zeros((0, 0))
        L[j, j] = math.sqrt(sjj)
        for i in range(j + 1, 6):
            sij = G[i, j]
            for k in range(j):
                sij -= L[i, k] * L[j, k]
            L[i, j] = sij / L[j, j]
    return L


@njit(cache=True)
def _residual_and_rhs(du, dv, y, w, c, s, su, sv, clipped, sgn, F, dFdt, he3, he5, t, r, J):  # type: ignore[no-untyped-def]
    """Pass 2: ``r``, ``J = A_k c`` (before the projections) and (J)'s summed right-hand side."""
    n = du.shape[0]
    nk = J.shape[1]
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
        if nk > 2:
            dF[2] = he3[i]
        if nk > 3:
            dF[3] = he5[i]
        pg = p * g - ri
        qg = q * g + ri
        for k in range(nk):
            wf = wi * dF[k]
            J[i, k] = wf * g  # A_k c, the projections taken off in pass 3
            al = wf * pg
            be = wf * qg
            RHS[0, k] += al
            RHS[1, k] += al * u
            RHS[2, k] += al * v
            RHS[3, k] += be
            RHS[4, k] += be * u
            RHS[5, k] += be * v
    return RHS


@njit(cache=True)
def edge_residual_jacobian(d, du, dv, y, w, x, min_sigma, r, J):  # type: ignore[no-untyped-def]
    """Fill ``r`` (N,) and ``J`` (N, len(x)) of model (R1)-(R2) at ``x = (delta, sigma, b...)``.

    ``d, du, dv, y, w`` as :class:`~pipeline.stages.response.edge_fit.EdgeFit` (``y = w E``);
    ``len(x) - 2`` (0, 1 or 2) odd shape terms. Returns False when the Gram matrix is
    singular (the caller then takes the NumPy path).

    With ``e = (1, u, v)`` (the offsets scaled), ``p = w (1 - F)`` and ``q = w F`` a
    row of ``A`` is ``(p e, q e)``, so ``G`` is three 3 x 3 blocks of ``e e^T``
    weighted by ``p^2, p q, q^2``; and since ``A_k = w F_k (-e, e)``, the two
    right-hand sides of (J) sum to ``(sum alpha_k e, sum beta_k e)`` with
    ``alpha_k = w F_k (p g - r)``, ``beta_k = w F_k (q g + r)``, ``g = (c_q - c_p) . e``.
    """
    n = d.shape[0]
    nk = x.shape[0]
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
    G, h = _profile_and_gram(d, du, dv, y, w, x, s, su, sv, F, dFdt, he3, he5, t)
    L = _cholesky(G)
    if L.shape[0] == 0:
        return False
    c = _chol_solve(L, h)
    RHS = _residual_and_rhs(du, dv, y, w, c, s, su, sv, clipped, sgn, F, dFdt, he3, he5, t, r, J)
    P = np.empty((6, nk))
    for k in range(nk):
        P[:, k] = _chol_solve(L, RHS[:, k].copy())
    # pass 3: J_k = A_k c - A P_k
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
