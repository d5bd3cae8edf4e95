"""Uncertainty of a fit of eq. (1): ``cov = sigma^2 (J^T J)^-1`` and the pin error it predicts."""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.kinematics.se3 import F64


def registered_field(Jw: F64, p: F64, kind: str) -> F64:
    """The pin error field's Jacobian after a registration, ``Pr J_w`` (3N, p).

    The error field ``dp = J_w dz`` (``J_w`` (N, 3, p)) minus its best-fit rigid
    (``absolute``) or similarity (``shape``) motion: to first order a projection
    ``Pr = I - Q Q^T`` onto the complement of the fields ``[I, -[p_i]x]`` (and
    ``p_i - mean`` for a similarity); ``raw``: no registration.
    """
    N = len(p)
    G = Jw.reshape(3 * N, -1)
    if kind != "raw":
        c = p - p.mean(axis=0)
        basis = [np.tile(np.eye(3), (N, 1))]
        rot = np.zeros((N, 3, 3))
        rot[:, 0, 1], rot[:, 0, 2] = c[:, 2], -c[:, 1]
        rot[:, 1, 0], rot[:, 1, 2] = -c[:, 2], c[:, 0]
        rot[:, 2, 0], rot[:, 2, 1] = c[:, 1], -c[:, 0]
        basis.append(rot.reshape(3 * N, 3))
        if kind == "shape":
            basis.append(c.reshape(3 * N, 1))
        Q, _ = np.linalg.qr(np.concatenate(basis, axis=1))
        G = G - Q @ (Q.T @ G)
    return np.asarray(G)


def predicted_errors(Jw: F64, cov: F64, p: F64, kind: str) -> F64:
    """Per-pose standard pin error the covariance predicts after a registration.

    With ``G = Pr J_w`` (:func:`registered_field`) and ``dz ~ N(0, cov)``, returns
    ``sqrt(trace_i(G cov G^T))`` per pose, (N,).
    """
    return field_errors(registered_field(Jw, p, kind), cov)


def field_errors(G: F64, cov: F64) -> F64:
    """``sqrt(trace_i(G cov G^T))`` per pose of a registered field ``G`` (3N, p), (N,)."""
    var = np.einsum("ij,jk,ik->i", G, cov, G).reshape(-1, 3).sum(axis=1)
    return np.asarray(np.sqrt(np.clip(var, 0.0, None)))


def with_pin_offset(cov_e: F64, pin_offset_cov: Any) -> F64:
    """The kinematic-and-pin covariance with the touch-ups' unseen constant pin offset added.

    The pose component of a touch-up's error (:func:`pipeline.stages.touchups.noise.
    pose_noise`, covariance ``Sigma_pose`` in the flange frame) varies from pose to pose
    around a mean no residual can see: a constant offset of every touch-up's pin is
    absorbed by the pin itself. Taking that mean as one more draw of the pose component,
    the pin's estimate carries it in full:

        cov_e[pin, pin] <- cov_e[pin, pin] + Sigma_pose                              (P1)

    (the pin is the last three of the ``E`` columns of ``cov_e``). On the independent
    generator's recordings the pin sat 44-47 um off along the view, against a pose
    component of 39-55 um (docs/error-budget.md).

    Parameters
    ----------
    cov_e : (E, E) covariance of the identified kinematic columns and the pin (m^2)
    pin_offset_cov : (3, 3) ``Sigma_pose`` (m^2, flange frame), or None / non-finite: nothing

    Returns
    -------
    (E, E) covariance
    """
    if pin_offset_cov is None:
        return cov_e
    S = np.asarray(pin_offset_cov, dtype=float)
    if S.shape != (3, 3) or not np.all(np.isfinite(S)) or not np.all(np.isfinite(cov_e)):
        return cov_e
    out = np.array(cov_e, dtype=float, copy=True)
    out[-3:, -3:] += 0.5 * (S + S.T)
    return out


def pin_offset_left(pin_offset_cov: Any, residual_cov: F64) -> Any:
    """(P1)'s ``Sigma_pose`` where the fit modelled part of what it measured (the print
    shape): along each principal axis ``v`` of ``Sigma_pose`` no more than the fit's
    residual still shows there::

        p_v <- min(p_v, v^T S_res v),    Sigma_pose <- V diag(p) V^T                  (P2)

    ``Sigma_pose`` is measured from the touch-up loop's small steps (pose to pose), so it
    holds whatever moves the touch-ups from pose to pose: an out-of-round print does,
    deterministically, and the print-shape fit takes it out of the residual. What it took
    out leaves no unseen mean; what is left (``S_res``, the fit's residual covariance in
    the flange frame) bounds it. On a Mitsuba render with out-of-round prints (LR Mate-like,
    seed 201): ``Sigma_pose`` 28 um along the view against a residual of 17 um, the
    verdict 0.0365 mm against 0.0139 mm true (2.6x) before (P2).

    Parameters
    ----------
    pin_offset_cov : (3, 3) ``Sigma_pose`` (m^2), or None: returned as it is
    residual_cov : (3, 3) ``S_res`` (m^2, flange frame)

    Returns
    -------
    (3, 3) list of lists, or ``pin_offset_cov`` itself when either is unusable
    """
    if pin_offset_cov is None:
        return None
    P = np.asarray(pin_offset_cov, dtype=float)
    S = np.asarray(residual_cov, dtype=float)
    if P.shape != (3, 3) or S.shape != (3, 3) or not np.all(np.isfinite(P) & np.isfinite(S)):
        return pin_offset_cov
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    seen = np.einsum("iv,ij,jv->v", V, 0.5 * (S + S.T), V)
    left = np.minimum(np.clip(lam, 0.0, None), np.clip(seen, 0.0, None))
    return ((V * left) @ V.T).tolist()


def residual_variance(r: F64, n_unknowns: int) -> tuple[float, int]:
    """Residual variance of a least-squares fit, ``sigma^2 = |r|^2 / (m - p)``.

    Parameters
    ----------
    r : (m,) residual vector at the solution
    n_unknowns : ``p``, the estimated unknowns

    Returns
    -------
    sigma2 : NaN when ``m <= p``
    dof : ``m - p``
    """
    dof = len(r) - int(n_unknowns)
    return (float(r @ r / dof) if dof > 0 else float("nan")), int(dof)


def covariance(J: F64, scale: F64, r: F64, n_extra: int = 0) -> tuple[F64, float, int]:
    """Covariance of the estimated unknowns of a least-squares fit.

    ``cov = sigma^2 (J^T J)^-1`` with ``sigma^2 = |r|^2 / (m - p - k)``, computed by
    the SVD of the column-scaled ``J S = U diag(s) V^T`` as
    ``S V diag(s^-2) V^T S sigma^2`` (singular values below ``1e-12 s_max``
    dropped: a pseudo-inverse), so that columns in radians and metres are
    conditioned alike (the scaling of :mod:`pipeline.stages.identify.stage`).

    Parameters
    ----------
    J : (m, p) Jacobian at the solution, columns of the estimated unknowns
    scale : (p,) column scale ``S`` (diagonal)
    r : (m,) residual vector at the solution
    n_extra : ``k``, unknowns estimated from the same residuals outside ``J``: the
        flange whitening's shape and a fitted print shape
        (:func:`pipeline.stages.identify.shape.spent_unknowns`)

    Returns
    -------
    cov : (p, p); NaN when ``m <= p + k``
    sigma2 : ``|r|^2 / (m - p - k)``, NaN when ``m <= p + k``
    dof : ``m - p - k``
    """
    U, sv, Vt = np.linalg.svd(J * scale, full_matrices=False)
    sigma2, dof = residual_variance(r, J.shape[1] + int(n_extra))
    good = sv > sv[0] * 1e-12
    Vs = Vt[good].T / sv[good]
    cov = (scale[:, None] * (Vs @ Vs.T)) * scale[None, :] * sigma2
    return cov, sigma2, int(dof)
