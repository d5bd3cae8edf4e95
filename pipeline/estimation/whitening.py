"""Whitening of the pin residuals in the flange (camera) frame.

A touch-up's error is fixed in the flange frame and far larger along the view
than across it: its 3x3 covariance ``S`` there is estimated from the fit and the
residuals are whitened, ``W R_i^T (p_i - t_k)`` (feasible generalised least
squares). Identification estimates ``S`` from every used row
(:func:`flange_whitening`); outlier rejection robustly, leaving out the rows
far in Mahalanobis distance (:func:`robust_flange_whitening`).
"""

from __future__ import annotations

import numpy as np

from pipeline.estimation.distributions import chi2_ppf
from pipeline.kinematics.se3 import F64
from pipeline.measurement.pin import Problem

#: unknowns the flange whitening estimates from the residuals it then weighs: the 3x3
#: covariance's six less its scale, which the variance factor carries
SHAPE_PARAMS = 5


def whitening_params(W: F64 | None) -> int:
    """Residual degrees of freedom a fit's flange whitening ``W`` spent (0 without one).

    The whitening's shape ``S / s^2`` is estimated from the same residuals the fit then
    weighs (feasible generalised least squares), so the variance factor is
    ``|r|^2 / (m - p - 5)`` (:func:`pipeline.estimation.uncertainty.covariance`)::

        f = m - p - SHAPE_PARAMS                                                    (W1)

    Without it the fit's covariance was too small for the weights it fitted: on simulated
    touch-level histories with isotropic pin noise (500 re-recordings of unchanged robots,
    ``benchmarks/bench_audit.py``' cell) the change test's ``T / r`` averaged 1.086 where
    ``F(30, 150)`` has 1.014, its p-values were not uniform (KS p 1e-4) and 2.6 % of the
    comparisons alarmed at ``alpha = 1 %``; with (W1) 1.017, KS p 0.74, 1.4 %. The same
    histories fitted without the whitening gave 0.99 (the cause is the weights, not the
    noise: one tenth of the noise gave the same p-values).
    """
    return SHAPE_PARAMS if W is not None else 0


def flange_residual_cov(prob: Problem, z: F64, n_free: int) -> F64 | None:
    """The pin residuals' covariance in the flange frame at ``z``, (3, 3) m^2.

    ``e_i = R_i^T (p_i - t_k)`` over the used rows; ``S = cov(e) m / (m - p)``
    (weighted, centred: a constant flange-frame offset is the pin's). None when fewer
    than 15 residual degrees of freedom remain (a 3x3 covariance from fewer is noise).
    """
    D = prob.data
    x, pin, tg = prob.split(z)
    p, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    e = np.einsum("nji,nj->ni", R, p - tg[D.tk])
    w = D.sw**2
    mu = (w[:, None] * e).sum(axis=0) / w.sum()
    c = e - mu
    dof = 3 * len(e) - (n_free + prob.layout.n_nuisance)
    if dof < 15:
        return None
    S = (w[:, None, None] * c[:, :, None] * c[:, None, :]).sum(axis=0) / w.sum()
    return np.asarray(S * (3 * len(e) / dof))


def flange_whitening(prob: Problem, z: F64, n_free: int) -> tuple[F64 | None, F64 | None]:
    """Whitening matrix of the pin residual in the flange frame, from the current fit.

    ``S`` of :func:`flange_residual_cov`; the returned ``W = s S^(-1/2)`` (eigenvalues
    floored at 1e-4 of the largest) keeps residuals in metres (``s^2`` is the mean
    variance). None when the residuals vanish (exact data) or fewer than 15 residual
    degrees of freedom remain.

    Returns
    -------
    W : (3, 3) or None
    sigma : (3,) standard deviations along the principal flange-frame axes, m
    """
    S = flange_residual_cov(prob, z, n_free)
    if S is None:
        return None, None
    lam, V = np.linalg.eigh(S)
    if lam.max() < (1e-9) ** 2:  # exact data: nothing to weigh
        return None, None
    lam = np.maximum(lam, lam.max() * 1e-4)
    s = np.sqrt(lam.mean())
    W = s * (V / np.sqrt(lam)) @ V.T
    return W, np.sqrt(lam)


def robust_flange_whitening(R: F64, r: F64, w: F64, n_est: int, flange: bool) -> F64:
    """Flange-frame whitening ``W`` of the pin residuals, as identification estimates it.

    A touch-up's error is fixed in the camera (flange) frame and larger along the
    view: ``S = cov(R_i^T r_i)`` (weighted), ``W = s V diag(lam^-1/2) V^T`` with
    ``S = V diag(lam) V^T``, ``s^2 = mean lam`` (so ``W`` only reshapes, it does not
    rescale). Unlike identification's, the covariance is estimated robustly (the
    touch-ups whose Mahalanobis distance exceeds the chi-square(3) 97.5 % point
    are left out, twice), so an outlier does not whiten itself away. Identity when
    identification used isotropic residuals (``flange`` false) or too few degrees
    of freedom are left (< 15).
    """
    if not flange or 3 * len(r) - n_est < 15:
        return np.eye(3)
    ef = np.einsum("nji,nj->ni", R, r)
    keep = np.ones(len(ef), dtype=bool)
    cut = chi2_ppf(0.975, 3)
    for _ in range(3):
        wk = w * keep
        mu = (wk[:, None] * ef).sum(axis=0) / wk.sum()
        c = ef - mu
        S = (wk[:, None, None] * c[:, :, None] * c[:, None, :]).sum(axis=0) / wk.sum()
        d2 = np.einsum("ni,ij,nj->n", c, np.linalg.pinv(S), c)
        new = d2 <= cut
        if new.sum() < max(6, len(ef) // 2) or np.array_equal(new, keep):
            break
        keep = new
    lam, V = np.linalg.eigh(S)
    if lam.max() < (1e-9) ** 2:
        return np.eye(3)
    lam = np.maximum(lam, lam.max() * 1e-4)
    return np.asarray(np.sqrt(lam.mean()) * (V / np.sqrt(lam)) @ V.T)
