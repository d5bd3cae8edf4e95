"""The image Jacobian and the servo step: one estimator, one step, for the offline
extraction and the live loop alike.

The image Jacobian ``J = d(u, v, 1/s) / d(p_flange)`` (3 x 3: flange translation
-> ``(du, dv, ds_inv)``; paper sec. 2.1) is fitted from *pairs* of still captures a
pure flange translation ``dF`` apart with measured changes ``dm``::

    dm_p = J dF_p,   J = argmin sum_p rho(dm_p - J dF_p)   (row by row)             (J1)

with Huber's ``rho`` (scale the residuals' MAD, threshold 1.5 of it). Two sources of
pairs feed it:

- the offline extraction (:mod:`pipeline.stages.touchups.stage`): consecutive still
  captures of the recorded loops, every target pooled (many pairs, some spoilt by
  a settling arm or a bad detection: the robust weights matter);
- the live loop's probe (:func:`pipeline.live.loop.estimate_jacobian`): the base
  capture and six shifts ``+-h`` along the flange axes, the pairs ``(+-h e_k,
  m(+-h e_k) - m(0))``. Their translations are axis-aligned and symmetric, so (J1)'s
  normal equations separate by column and each column is the central difference
  ``(m(+h e_k) - m(-h e_k)) / (2 h)`` (truncation ``O(h^2)``: the curvature of the
  projection cancels), whatever the robust weights (a column's two residuals are
  equal).

The loop keeps a refinement of its own between probes: Broyden's rank-one update
from each servo step (:func:`pipeline.live.loop.broyden_update`).

The step that cancels ``gain`` of an image error ``e_T``, linearising ``e_T(p + dp)
~ e_T(p) + J dp`` and asking for ``(1 - gain) e_T``, is the residual correction
(:func:`pipeline.measurement.image.residual_correction`, ``d_F = -J^-1 e_T``) times
the gain::

    dp = gain d_F,   clipped to ``max_step_m`` along its own direction               (J2)
"""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.measurement.image import residual_correction


def _huber_rows(X: np.ndarray, Y: np.ndarray, iters: int = 10) -> np.ndarray:
    """Row-wise robust fit of ``Y = X J^T``: ``X (N, 3)``, ``Y (N, 3)`` -> ``J (3, 3)``."""
    J = np.zeros((Y.shape[1], X.shape[1]))
    for r in range(Y.shape[1]):
        y = Y[:, r]
        w = np.ones(len(y))
        coef = np.zeros(X.shape[1])
        for _ in range(iters):
            sw = np.sqrt(w)
            coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
            res = y - X @ coef
            sc = 1.4826 * float(np.median(np.abs(res))) + 1e-15
            k = 1.5 * sc
            a = np.abs(res)
            w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
        J[r] = coef
    return J


def fit_image_jacobian(dF: np.ndarray, dm: np.ndarray, min_pairs: int = 4) -> np.ndarray | None:
    """(J1): the image Jacobian from pairs, ``dm (N, 3) ~ J dF (N, 3)``; None if ill-posed.

    Parameters
    ----------
    dF : (N, 3) flange-frame translations (m)
    dm : (N, 3) changes of ``(u, v, s_inv)`` (px, px, 1/px)
    min_pairs : fewer pairs are ill-posed (the live probe's six pairs are exact)

    Returns
    -------
    (3, 3) ``J`` with ``dm = J dF``, or None with fewer than ``min_pairs`` pairs or
    translations that do not span 3-D (singular value ratio < 0.05).
    """
    dF = np.asarray(dF, dtype=float)
    dm = np.asarray(dm, dtype=float)
    if len(dF) < max(min_pairs, 3):
        return None
    sv = np.linalg.svd(dF, compute_uv=False)
    if sv[-1] < 0.05 * sv[0]:
        return None
    return _huber_rows(dF, dm)


def servo_step(J: F64, e: F64, gain: float, max_step_m: float) -> F64:
    """(J2): the flange step that cancels ``gain`` of the error ``e_T``.

    Parameters
    ----------
    J : (3, 3) image Jacobian
    e : (3,) ``e_T``
    gain : float
    max_step_m : a longer step is scaled down to this length (a poor Jacobian or a
        far start cannot throw the arm)

    Returns
    -------
    (3,) ``dp_flange`` (m, flange frame); zero where ``J`` is singular.
    """
    dp = np.asarray(gain * residual_correction(J, e), dtype=np.float64)
    n = float(np.linalg.norm(dp))
    if n > max_step_m:
        dp = np.asarray(dp * (max_step_m / n), dtype=np.float64)
    return dp
