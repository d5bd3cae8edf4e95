"""The edge model (R1)-(R2) of :mod:`pipeline.stages.image.response_estimate`, fitted with its Jacobian.

One edge profile (pixels at signed distance ``d`` from the detected contour,
offsets ``du, dv`` from its centre, linearised grey ``E`` and weights
``w = 1 / (dE/dI)``) under a trial response is fitted by variable projection:
with the nonlinear parameters ``x = (delta, sigma, b3, b5)``::

    t = (d - delta) / s,   s = max(|sigma|, 0.05)
    F = Phi(t) + b3 He3(t) phi(t) + b5 He5(t) phi(t)                     (R2)
    A(x) = w [1-F, (1-F) du, (1-F) dv, F, F du, F dv]        (N, 6)
    c(x) = A^+ (w E),   r(x) = A c - w E                                 (R1)

and Levenberg-Marquardt (MINPACK) minimises ``|r|^2`` over ``x``. The six
levels ``c`` are linear, eliminated by the projection.

The Jacobian of the projected residual (Golub and Pereyra's, exact; no
approximation) with ``P = Q Q^T`` the projector on ``A``'s columns
(``A = Q R``) and ``A_k = dA/dx_k``::

    dr/dx_k = (I - P) A_k c - Q R^-T (A_k^T r)                            (J)

``A`` depends on ``x`` only through ``F``, so ``A_k = w F_k G`` with ``F_k =
dF/dx_k`` and ``G = [-1, -du, -dv, 1, du, dv]``: ``A_k c = w F_k (G c)`` and
``A_k^T r = G^T (w F_k r)``. The derivatives of ``F``, with ``d/dt [He_n phi]
= -He_{n+1} phi``::

    dF/dt   = phi (1 - b3 He4 - b5 He6)
    dF/ddelta = -dF/dt / s,  dF/dsigma = -(dF/dt) t / s sign(sigma) (0 where s is clipped)
    dF/db3 = He3 phi,        dF/db5 = He5 phi

Before, MINPACK differenced the residual (five residuals, each an SVD
least squares, per Jacobian): the same fit to its tolerance (the residual
sums agree to ~1e-12 relative), at a third of the cost
(``tests/test_response_fit.py`` holds (J) to finite differences).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_triangular
from scipy.optimize import leastsq
from scipy.special import ndtr

from pipeline.kinematics.se3 import F64

try:  # the compiled residual and Jacobian (same model, one pass per term)
    from pipeline.stages.response import _edge_jit
except ImportError:  # pragma: no cover - numba missing: the NumPy path
    _edge_jit = None  # type: ignore[assignment]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
#: the smallest edge width the model takes (px): below it ``sigma`` is clipped
MIN_SIGMA = 0.05


def edge_spread(t: F64, b: F64) -> F64:
    """The edge profile of (R1)-(R2) at ``t = (d - delta) / sigma``, (N,).

    ``F = Phi(t) + b3 He3(t) phi(t) + b5 He5(t) phi(t)`` (``He`` the Hermite
    polynomials, ``phi`` the normal density): the edge of *any* symmetric point
    spread function is ``1/2`` plus an odd function of ``t``, and these two odd terms
    take a disk (defocus) or a box (pixel) kernel's profile where an erf alone
    leaves a residual of a few grey levels on a sharp edge. A response error bends
    the profile by an even function (``c F (1 - F)``) and cannot hide in them.
    """
    F: F64 = ndtr(t)
    if len(b):
        ph = np.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi)
        t2 = t * t
        F = F + b[0] * (t * t2 - 3.0 * t) * ph
        if len(b) > 1:
            F = F + b[1] * (t * t2 * t2 - 10.0 * t * t2 + 15.0 * t) * ph
    return F


def edge_spread_grad(t: F64, b: F64) -> tuple[F64, F64, list[F64]]:
    """``F`` of :func:`edge_spread`, ``dF/dt`` and ``[dF/db3, dF/db5]`` (each (N,)).

    Uses ``d/dt [He_n(t) phi(t)] = -He_{n+1}(t) phi(t)`` (module docstring).
    """
    F: F64 = ndtr(t)
    ph = np.exp(-0.5 * t * t) * _INV_SQRT_2PI
    dFdt: F64 = ph
    dFdb: list[F64] = []
    if len(b):
        t2 = t * t
        he3 = (t * t2 - 3.0 * t) * ph
        he4 = (t2 * t2 - 6.0 * t2 + 3.0) * ph
        F = F + b[0] * he3
        dFdt = dFdt - b[0] * he4
        dFdb.append(he3)
        if len(b) > 1:
            he5 = (t * t2 * t2 - 10.0 * t * t2 + 15.0 * t) * ph
            he6 = (t2 * t2 * t2 - 15.0 * t2 * t2 + 45.0 * t2 - 15.0) * ph
            F = F + b[1] * he5
            dFdt = dFdt - b[1] * he6
            dFdb.append(he5)
    return F, dFdt, dFdb


class EdgeFit:
    """Residual (R1) and its Jacobian (J) of one edge profile, for ``least_squares``.

    Parameters
    ----------
    d, du, dv : (N,) signed distance to the contour and offsets from its centre, px
    y : (N,) weighted linearised grey ``w E``
    w : (N,) weights ``1 / (dE/dI)``
    harmonics : (N, 2K), optional: the edge's harmonics around the contour
        (:func:`pipeline.stages.image.response_estimate.edge_harmonics`): then ``x = (delta,
        sigma, a_1..a_K, b_1..b_K)``, ``t = (d - delta - C x[2:]) / s``, ``F = Phi(t)`` (no
        shape terms) and ``dF/dx_{2+j} = -(dF/dt) C_j / s``
    """

    def __init__(
        self, d: F64, du: F64, dv: F64, y: F64, w: F64, harmonics: F64 | None = None
    ) -> None:
        self.d, self.du, self.dv, self.y, self.w = d, du, dv, y, w
        self.C = harmonics
        self._cache: list[tuple[bytes, tuple[F64, ...]]] = []

    def _parts(self, x: F64) -> tuple[F64, ...]:
        key = x.tobytes()
        for k, parts in self._cache:
            if k == key:
                return parts
        parts = self._compute(x)
        self._cache = [(key, parts), *self._cache[:1]]
        return parts

    def _compute(self, x: F64) -> tuple[F64, ...]:
        """The residual (first) and what (J) needs at ``x``."""
        s = abs(x[1])
        clipped = s < MIN_SIGMA
        s = max(s, MIN_SIGMA)
        if self.C is None:
            t = (self.d - x[0]) / s
            F, dFdt, dFdb = edge_spread_grad(t, x[2:])
        else:  # the edge's own harmonics instead of the shape terms (edge_harmonics)
            t = (self.d - x[0] - self.C @ x[2:]) / s
            F, dFdt, dFdb = edge_spread_grad(t, x[:0])
        wF, w1F = self.w * F, self.w * (1.0 - F)
        du, dv = self.du, self.dv
        A = np.stack([w1F, w1F * du, w1F * dv, wF, wF * du, wF * dv], 1)
        Q, R = np.linalg.qr(A)
        c = solve_triangular(R, Q.T @ self.y, check_finite=False)
        r = A @ c - self.y
        return (r, Q, R, c, t, dFdt, *dFdb, np.array([s, float(clipped), np.sign(x[1])]))

    def residual(self, x: F64) -> F64:
        """``r(x) = A c - w E``, (N,)."""
        return self._parts(x)[0]

    def jacobian(self, x: F64) -> F64:
        """``dr/dx`` (N, len(x)) by (J)."""
        r, Q, R, c, t, dFdt, *rest = self._parts(x)
        dFdb, (s, clipped, sgn) = rest[:-1], rest[-1]
        du, dv, w = self.du, self.dv, self.w
        dF = [-dFdt / s, (np.zeros_like(t) if clipped else -dFdt * t / s * sgn), *dFdb]
        if self.C is not None:
            dF += [-dFdt / s * ck for ck in self.C.T]
        Gc = (c[3] - c[0]) + (c[4] - c[1]) * du + (c[5] - c[2]) * dv
        wr = w * r
        J = np.empty((len(r), len(dF)))
        # (I - P) A_k c for every k at once, then the Q R^-T (A_k^T r) terms
        AkC = np.stack([w * f * Gc for f in dF], 1)
        J[:] = AkC - Q @ (Q.T @ AkC)
        Z = np.empty((6, len(dF)))
        for k, f in enumerate(dF):
            g = f * wr
            s0, s1, s2 = g.sum(), (g * du).sum(), (g * dv).sum()
            Z[:, k] = (-s0, -s1, -s2, s0, s1, s2)
        J -= Q @ solve_triangular(R, Z, trans="T", check_finite=False)
        return J


class CompiledEdgeFit(EdgeFit):
    """:class:`EdgeFit` (no harmonics) through :mod:`pipeline.stages.response._edge_jit`.

    The residual and the Jacobian of one ``x`` come from one call of the compiled
    kernel (MINPACK asks for both at each accepted step), kept as :class:`EdgeFit`
    keeps its parts. Falls back to :class:`EdgeFit`'s at an ``x`` where the kernel's
    Gram matrix is singular.
    """

    def _compute(self, x: F64) -> tuple[F64, ...]:
        n = len(self.d)
        r, J = np.empty(n), np.empty((n, len(x)))
        ok = _edge_jit.edge_residual_jacobian(
            self.d, self.du, self.dv, self.y, self.w, np.ascontiguousarray(x), MIN_SIGMA, r, J
        )
        if not ok:
            ref = EdgeFit(self.d, self.du, self.dv, self.y, self.w)
            return ref.residual(x), ref.jacobian(x)
        return r, J

    def jacobian(self, x: F64) -> F64:
        """``dr/dx`` (N, len(x)) by (J)."""
        return self._parts(x)[1]


def fit_edge(
    d: F64,
    du: F64,
    dv: F64,
    E: F64,
    w: F64,
    x0: F64,
    xtol: float = 1e-10,
    compiled: bool = True,
) -> tuple[float, F64]:
    """Fit model (R1)-(R2) to one profile: residual sum (weighted grey^2) and ``x``.

    Levenberg-Marquardt by MINPACK's ``lmder`` (``scipy.optimize.leastsq``, the
    routine ``least_squares(method="lm")`` wraps, with its settings: ``ftol = gtol =
    1e-8``, at most ``100 len(x)`` evaluations, ``factor`` 100, scaling from the
    Jacobian's columns), without that wrapper's per-call checks.

    Parameters
    ----------
    d, du, dv, E, w : (N,) as :class:`EdgeFit` (``E`` linearised grey, unweighted)
    x0 : (2 + n_shape,) start ``(delta, sigma[, b3, b5])``
    xtol : MINPACK's relative step tolerance
    compiled : the residual and Jacobian from the compiled kernel
        (:class:`CompiledEdgeFit`; the NumPy :class:`EdgeFit` when False or numba is missing)

    Returns
    -------
    rss : float, ``|r|^2`` at the solution
    x : the solution (``sigma`` may come back negative: its sign is immaterial)
    """
    y = E * w
    fit: EdgeFit | CompiledEdgeFit
    if compiled and _edge_jit is not None:
        fit = CompiledEdgeFit(d, du, dv, y, w)
    else:
        fit = EdgeFit(d, du, dv, y, w)
    x0 = np.asarray(x0, dtype=float)
    x, _, info, _, _ = leastsq(
        fit.residual,
        x0,
        Dfun=fit.jacobian,
        full_output=True,
        xtol=xtol,
        ftol=1e-8,
        gtol=1e-8,
        maxfev=100 * len(x0),
        factor=100.0,
    )
    r = info["fvec"]
    return float(np.sum(r**2)), np.asarray(x, dtype=float)


def warm_edge_fit() -> None:
    """One compiled fit of a small synthetic edge, so the kernel is compiled (or loaded).

    Called by :func:`pipeline.stages.detect.precompile.compile_detector` (at install and
    before a run's first image) beside the detector's own warm-up.
    """
    if _edge_jit is None:
        return
    d = np.linspace(-5.0, 5.0, 64)
    du, dv = np.cos(3.0 * d), np.sin(2.0 * d)
    E = 0.2 + 0.6 * ndtr(d / 0.8)
    fit_edge(d, du, dv, E, np.ones_like(d), np.array([0.1, 0.7, 0.0, 0.0]))
