"""The edge model's fit with its analytic Jacobian (pipeline.stages.response.edge_fit).

The camera-response estimate fits model (R1)-(R2) some 250 times a recording;
MINPACK used to difference the residual for its Jacobian. These tests hold the
analytic Jacobian to finite differences, the fit to the differenced fit, and the
estimate's figures to the estimate made with the differenced fits, and the
compiled kernel (``_edge_jit``) to the NumPy reference.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative
from test_response import renders, srgb_encode

import pipeline.stages.image.response_estimate as rest
from pipeline.stages.response.curve import Response
from pipeline.stages.response.edge_fit import CompiledEdgeFit, EdgeFit, edge_spread, fit_edge


def profile(seed: int = 1, n: int = 900):
    """A noisy blurred edge with uneven levels, (d, du, dv, grey in [0, 1])."""
    rng = np.random.default_rng(seed)
    d, du, dv = rng.uniform(-6, 6, n), rng.uniform(-20, 20, n), rng.uniform(-20, 20, n)
    F = edge_spread((d - 0.2) / 0.9, np.array([0.02, -0.01]))
    g = (0.2 + 0.001 * du) * (1 - F) + (0.8 - 0.002 * dv) * F
    return d, du, dv, np.clip(g + rng.normal(0, 0.008, n), 0.01, 0.99)


def fd_fit(d, du, dv, E, w, x0, xtol=1e-10):
    """The fit as it was: MINPACK with a differenced Jacobian, residual by lstsq."""

    def res(x):
        F = edge_spread((d - x[0]) / max(abs(x[1]), 0.05), x[2:])
        A = np.stack([1 - F, (1 - F) * du, (1 - F) * dv, F, F * du, F * dv], 1) * w[:, None]
        coef, *_ = np.linalg.lstsq(A, E * w, rcond=None)
        return A @ coef - E * w

    sol = least_squares(res, x0, method="lm", xtol=xtol)
    return float(np.sum(sol.fun**2)), sol.x


@pytest.mark.parametrize("curve", [Response("linear"), Response("srgb"), Response("gamma", 1.7)])
@pytest.mark.parametrize("x", [(0.1, 0.7, 0.03, 0.01), (-0.3, -1.2, -0.05, 0.02), (0.2, 0.9)])
def test_analytic_jacobian_matches_finite_differences(curve, x):
    d, du, dv, g = profile()
    w = 1.0 / np.maximum(curve.slope(g), 1e-6)
    fit = EdgeFit(d, du, dv, curve.to_linear(g) * w, w)
    x = np.array(x)
    J = fit.jacobian(x)
    Jn = approx_derivative(fit.residual, x, method="3-point")
    assert J.shape == (len(d), len(x))
    assert np.abs(J - Jn).max() < 1e-7 * np.abs(Jn).max()


def test_harmonics_jacobian_matches_finite_differences():
    """The edge's own harmonics around the contour (edge_harmonics): raw grey, no weights."""
    d, du, dv, g = profile(seed=2)
    psi = np.arctan2(dv, du)
    ks = np.arange(1, rest.ROUND_HARMONICS + 1)
    C = np.concatenate([np.cos(np.outer(psi, ks)), np.sin(np.outer(psi, ks))], axis=1)
    fit = EdgeFit(d, du, dv, g, np.ones_like(g), harmonics=C)
    x = np.array([0.1, 0.8, *np.linspace(-0.05, 0.05, C.shape[1])])
    J = fit.jacobian(x)
    Jn = approx_derivative(fit.residual, x, method="3-point")
    assert J.shape == (len(d), 2 + C.shape[1])
    assert np.abs(J - Jn).max() < 1e-7 * np.abs(Jn).max()


def test_fit_equals_the_differenced_fit():
    d, du, dv, g = profile(seed=3)
    for curve in (Response("linear"), Response("srgb"), Response("gamma", 2.4)):
        E, w = curve.to_linear(g), 1.0 / np.maximum(curve.slope(g), 1e-6)
        x0 = np.array([0.0, 0.8, 0.0, 0.0])
        rss, x = fit_edge(d, du, dv, E, w, x0)
        rss_fd, x_fd = fd_fit(d, du, dv, E, w, x0)
        assert rss == pytest.approx(rss_fd, rel=1e-10)
        assert np.allclose(x[:2] * [1, np.sign(x[1])], x_fd[:2] * [1, np.sign(x_fd[1])], atol=1e-7)


def test_estimate_unchanged_against_differenced_fits(monkeypatch):
    """Seeded sRGB renders: the same curve, power law, margins and figures either way."""
    images = [img for img, _ in renders(srgb_encode, n=6, seed=9)]
    fast = rest.estimate_response(images, max_images=6)
    monkeypatch.setattr(rest, "fit_edge", fd_fit)
    slow = rest.estimate_response(images, max_images=6)
    assert fast.response.spec == slow.response.spec == "srgb"
    assert fast.note == slow.note
    for key in ("gamma_fit", "delta_linear", "delta_srgb", "sigma_grey", "illumination_gradient"):
        assert getattr(fast, key) == pytest.approx(getattr(slow, key), rel=1e-6), key
    assert fast.votes_srgb == slow.votes_srgb and fast.n_pixels == slow.n_pixels


def test_a_profile_is_fitted_once_per_curve(monkeypatch):
    """The figures taken at the best power law (noise, edge width, light) reuse its fit."""
    images = [img for img, _ in renders(lambda E: E, n=4, seed=6)]
    fits: list[tuple[int, bytes]] = []

    def counting(d, du, dv, E, w, x0, **k):
        fits.append((id(d), E.tobytes()))
        return fit_edge(d, du, dv, E, w, x0, **k)

    monkeypatch.setattr(rest, "fit_edge", counting)
    est = rest.estimate_response(images, max_images=4)
    assert est.n_images == 4
    assert len(fits) >= 4 * 13  # the grid of 10, the bounded search, linear and sRGB
    assert len(fits) == len(set(fits))


@pytest.mark.parametrize("curve", [Response("linear"), Response("srgb"), Response("gamma", 1.7)])
@pytest.mark.parametrize(
    "x",
    [(0.1, 0.7, 0.03, 0.01), (-0.3, -1.2, -0.05, 0.02), (0.2, 0.9), (0.0, 0.01, 0.01, 0.0)],
)
def test_compiled_kernel_equals_the_numpy_reference(curve, x):
    """Residual and Jacobian (J) of the compiled kernel: the reference's to 1e-9 (a clipped
    sigma, 0.01 < MIN_SIGMA, included), and (J) to finite differences."""
    d, du, dv, g = profile(seed=4)
    w = 1.0 / np.maximum(curve.slope(g), 1e-6)
    y = curve.to_linear(g) * w
    ref, fast = EdgeFit(d, du, dv, y, w), CompiledEdgeFit(d, du, dv, y, w)
    x = np.array(x)
    r, J = fast.residual(x), fast.jacobian(x)
    assert np.abs(r - ref.residual(x)).max() < 1e-9 * np.abs(y).max()
    assert np.abs(J - ref.jacobian(x)).max() < 1e-9 * np.abs(J).max()
    Jn = approx_derivative(fast.residual, x, method="3-point")
    assert np.abs(J - Jn).max() < 1e-7 * np.abs(Jn).max()


def test_compiled_fit_equals_the_numpy_fit():
    """The same MINPACK steps either way: residual sums to 1e-12, solutions to 1e-9."""
    d, du, dv, g = profile(seed=5)
    for curve in (Response("linear"), Response("srgb"), Response("gamma", 0.7)):
        E, w = curve.to_linear(g), 1.0 / np.maximum(curve.slope(g), 1e-6)
        x0 = np.array([0.0, 0.8, 0.0, 0.0])
        rss, x = fit_edge(d, du, dv, E, w, x0)
        rss_np, x_np = fit_edge(d, du, dv, E, w, x0, compiled=False)
        assert rss == pytest.approx(rss_np, rel=1e-12)
        assert np.allclose(x, x_np, rtol=0, atol=1e-9)


def test_minpack_without_the_wrapper_takes_the_same_steps():
    """``leastsq`` with ``least_squares(method="lm")``'s settings: bit-identical results."""
    d, du, dv, g = profile(seed=6)
    E, w = g, np.ones_like(g)
    x0 = np.array([0.0, 0.8, 0.0, 0.0])
    rss, x = fit_edge(d, du, dv, E, w, x0, compiled=False)
    fit = EdgeFit(d, du, dv, E * w, w)
    sol = least_squares(fit.residual, x0, jac=fit.jacobian, method="lm", xtol=1e-10)
    assert np.array_equal(x, sol.x) and rss == float(np.sum(sol.fun**2))
