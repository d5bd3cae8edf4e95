"""pipeline.estimation: eq. (1)'s analytic Jacobian against finite differences, the
covariance against the textbook formula, whitening against a known noise covariance."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.evaluate import perturbed_chain, random_deviations, synthetic_touchups
from pipeline.estimation.uncertainty import covariance
from pipeline.estimation.whitening import robust_flange_whitening
from pipeline.kinematics import load_chain
from pipeline.measurement.pin import Problem, initial_pin_targets
from pipeline.models import make_model
from pipeline.robots import builtin_urdf
from pipeline.stages.identify.data import prepare_data
from pipeline.stages.identify.types import IdentifyConfig

PIN = np.array([0.0167, -0.0101, 0.2524])
CENTRE = np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32])


def _problem(model: str, whitened: bool, gauge: bool) -> tuple[Problem, np.ndarray]:
    """A seeded 3-target problem with a known distance; a point away from the solution."""
    nominal = load_chain(builtin_urdf("lrmate"), "base_link", "flange")
    rng = np.random.default_rng(4)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    table, targets = synthetic_touchups(true, PIN, 3, 5, rng, noise_pin_m=1e-4, q_centre=CENTRE)
    table["weight"] = rng.uniform(0.5, 2.0, len(table))  # unequal weights: sqrt(w) rows
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    config = IdentifyConfig(distances=[(0, 2, d02)])
    data = prepare_data(table, nominal, config)
    em = make_model(model, nominal)
    g = rng.normal(size=em.n_params) if gauge else None
    prob = Problem(em, data, config, gauge=g)
    if whitened:
        A = rng.normal(size=(3, 3))
        prob.W = A @ A.T + np.eye(3)
    x = rng.normal(scale=1e-3, size=em.n_params)
    pin, tg = initial_pin_targets(em, data, x)
    return prob, prob.join(x, pin + 1e-3, tg + rng.normal(scale=1e-3, size=tg.shape))


def _central_differences(f, z: np.ndarray, h: float = 1e-7) -> np.ndarray:
    cols = []
    for k in range(z.size):
        dz = np.zeros_like(z)
        dz[k] = h
        cols.append((f(z + dz) - f(z - dz)) / (2 * h))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("model,gauge", [("full", False), ("full", True), ("poe", False)])
def test_jacobian_of_eq1_matches_central_differences(model, gauge) -> None:
    prob, z = _problem(model, whitened=False, gauge=gauge)
    J, fd = prob.jac(z), _central_differences(prob.fun, z)
    assert np.abs(J - fd).max() < 1e-7 * np.abs(fd).max(), np.abs(J - fd).max()
    # the rows: 3 per touch-up, one per known distance, one gauge row
    assert J.shape[0] == 3 * len(prob.data.q) + 1 + int(gauge)


@pytest.mark.parametrize("model", ["full", "poe"])
def test_whitened_jacobian_is_gauss_newton_in_the_rotation(model) -> None:
    """Whitened rows ``W R_i(x)^T (p_i - t_k)``: the Jacobian holds ``W R^T`` fixed.

    The pin and target columns are exact; each kinematic column lacks exactly the
    term ``W (dR_i^T/dx) (p_i - t_k)``, which vanishes with the residual (the
    feasible generalised least squares of identification linearises so).
    """
    prob, z = _problem(model, whitened=True, gauge=False)
    J, fd = prob.jac(z), _central_differences(prob.fun, z)
    nf, n = len(prob.free), 3 * len(prob.data.q)
    scale = np.abs(fd).max()
    assert np.abs(J[:, nf:] - fd[:, nf:]).max() < 1e-7 * scale
    x, pin, tg = prob.split(z)
    D, em, W = prob.data, prob.model, prob.W
    p, _, _ = em.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    e = (p - tg[D.tk]) * D.sw[:, None]

    def rotated(xv: np.ndarray) -> np.ndarray:  # W R(xv)^T e, e held fixed
        _, R, _ = em.pin_and_jacobian(xv, D.q, pin + D.d, jac=False)
        return np.einsum("ab,ncb,nc->na", W, R, e).ravel()

    omitted = _central_differences(rotated, x)[:, prob.free]
    gap = np.abs(J[:n, :nf] + omitted - fd[:n, :nf]).max()
    assert gap < 1e-7 * scale, gap
    assert np.abs(omitted).max() > 1000 * gap  # the check tells the two apart


def test_covariance_is_sigma2_times_the_inverse_normal_matrix() -> None:
    rng = np.random.default_rng(2)
    J = rng.normal(size=(40, 6)) * np.array([1e3, 1.0, 1e-2, 1.0, 5.0, 1e-3])
    scale = 1.0 / np.linalg.norm(J, axis=0)
    r = rng.normal(size=40)
    cov, sigma2, dof = covariance(J, scale, r)
    assert dof == 34 and sigma2 == pytest.approx(float(r @ r) / 34)
    reference = sigma2 * np.linalg.inv(J.T @ J)
    assert np.allclose(cov, reference, rtol=1e-8, atol=0)
    _, s2, d = covariance(J[:6], scale, r[:6])  # no redundancy: sigma undefined
    assert d == 0 and np.isnan(s2)


def test_robust_whitening_undoes_a_known_flange_covariance_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    n = 400
    S = np.diag([1e-8, 4e-8, 1e-6])  # along the view (z) 10x the across
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    S = Q @ S @ Q.T
    e_flange = rng.multivariate_normal(np.zeros(3), S, size=n)
    e_flange[:8] += 0.05  # a few gross errors: left out of the estimate
    R = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(n)])
    r_base = np.einsum("nij,nj->ni", R, e_flange)  # residuals in the base frame
    W = robust_flange_whitening(R, r_base, np.ones(n), 10, True)
    white = W @ S @ W.T  # W only reshapes: s^2 I with s^2 the mean eigenvalue of S
    s2 = np.trace(S) / 3
    assert np.allclose(white, s2 * np.eye(3), atol=0.15 * s2)
    assert np.array_equal(robust_flange_whitening(R, r_base, np.ones(n), 10, False), np.eye(3))
