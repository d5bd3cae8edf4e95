"""The detection noise of a touch-up, measured from its repeated final captures.

At convergence a touch-up takes several captures at one flange pose
(:mod:`pipeline.stages.touchups.stage`, step 5). Their measurements ``m = (u, v, 1/s)``
differ only by what changes from one image to the next at a fixed pose: sensor
noise, flicker, a camera still swinging. Pooled over every touch-up with ``n_k``
captures, with ``mbar_k`` its mean::

    Sigma_m = sum_k sum_j (m_kj - mbar_k)(m_kj - mbar_k)^T / sum_k (n_k - 1)      (N1)

and, through the image Jacobian (the correction ``d_F = -J^{-1} e_T``), one
capture's noise in the flange frame and that of a touch-up's averaged correction::

    Sigma_d = J^{-1} Sigma_m J^{-T},        Sigma_dbar = Sigma_d / n_eff               (N2)

(``n_eff`` the harmonic mean of the ``n_k``). This is what the touch-ups' pin
positions would scatter by if detection noise were their only error: an
independent prediction of the fit's residual, against which
:mod:`pipeline.stages.outliers.adequacy` tests the fit. It is blind, by construction, to
what stays the same at one pose and changes between poses (a response curve,
defocus, uneven light, an out-of-round print seen from another angle): those are
exactly the errors the test is there to reveal.

It is also blind to a **pose component**: an error of the detected ellipse that is
the same in every capture at one pose and new at the next, because the disc's edge
falls on the pixel grid anew (measured on an independent generator's ideal
recordings: 0.010 px of long axis per pose against 0.0075 px per capture, 48 um
along the view at a 0.22 m stand-off; docs/error-budget.md). Consecutive still
captures a small pure translation apart (the loop's last steps, the Jacobian's
pairs) see it: their change less the Jacobian's prediction, ``r = dm - J dF``,
holds both poses' components and both captures' noise, so per measurement row
``r``, from the pairs whose predicted image change is small (a Jacobian error then
adds little), with ``sd_r`` a robust (MAD) standard deviation::

    sigma_pose,r^2 = max(0, sd_r^2 / 2 - Sigma_m,rr)                                (N3)
    Sigma_touchup = Sigma_dbar + J^-1 diag(sigma_pose^2) J^-T                        (N4)

A bias that changes smoothly with the view (a wrong camera curve, defocus, a lamp)
is nearly the same at two poses a step apart, so (N3) leaves it to the adequacy test.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pipeline.kinematics.se3 import F64


def capture_noise(
    uses: list[list[int]], u: F64, v: F64, s: F64, J: F64, s0: float
) -> dict[str, Any]:
    """(N1)-(N2) from the final captures of each touch-up.

    Parameters
    ----------
    uses : per touch-up the capture indices averaged at its final pose
    u, v, s : (n,) every capture's centre and long axis, px
    J : (3, 3) image Jacobian ``d(u, v, 1/s) / d d_F`` (per metre, flange frame)
    s0 : designated long axis, px (the centre rows hold at it)

    Returns
    -------
    dict (JSON-able): ``n_touchups`` with two or more finite captures, ``dof`` of (N1),
    ``n_eff``, ``sd_px`` the per-capture standard deviations of ``u, v, s``,
    ``cov_flange_m2`` (3, 3) Sigma_d of one capture, ``sd_touchup_um`` (3,) the
    averaged correction's standard deviations along the flange axes, and
    ``rms_touchup_um`` ``sqrt(tr Sigma_dbar)``; figures NaN without repeated captures.
    """
    S = np.zeros((3, 3))
    dof = 0
    ns: list[int] = []
    for use in uses:
        if len(use) < 2:
            continue
        idx = np.asarray(use, dtype=int)
        m = np.stack([u[idx], v[idx], 1.0 / s[idx]], axis=1)
        m = m[np.all(np.isfinite(m), axis=1)]
        if len(m) < 2:
            continue
        dm = m - m.mean(axis=0)
        S += dm.T @ dm
        dof += len(m) - 1
        ns.append(len(m))
    nan3 = [float("nan")] * 3
    out: dict[str, Any] = {
        "n_touchups": len(ns),
        "dof": dof,
        "n_eff": float("nan"),
        "sd_px": nan3,
        "cov_flange_m2": [nan3, nan3, nan3],
        "sd_touchup_um": nan3,
        "rms_touchup_um": float("nan"),
    }
    if dof < 3 or not np.all(np.isfinite(J)):
        return out
    Sm = S / dof
    Ji = np.linalg.inv(np.asarray(J, dtype=float))
    Sd = Ji @ Sm @ Ji.T
    n_eff = len(ns) / float(np.sum(1.0 / np.asarray(ns, dtype=float)))
    sd_s = float(np.sqrt(Sm[2, 2])) * s0 * s0  # d(1/s) = -ds / s^2 at s0
    out.update(
        n_eff=n_eff,
        sd_px=[float(np.sqrt(Sm[0, 0])), float(np.sqrt(Sm[1, 1])), sd_s],
        cov_flange_m2=Sd.tolist(),
        sd_touchup_um=(1e6 * np.sqrt(np.clip(np.diag(Sd), 0, None) / n_eff)).tolist(),
        rms_touchup_um=float(1e6 * np.sqrt(max(np.trace(Sd), 0.0) / n_eff)),
    )
    return out


def pose_noise(
    dF: F64,
    dm: F64,
    J: F64,
    capture: dict[str, Any],
    s0: float,
    *,
    max_change_px: float = 3.0,
    min_pairs: int = 8,
) -> dict[str, Any]:
    """(N3)-(N4): the pose component from the Jacobian's pairs, and the complete noise.

    Parameters
    ----------
    dF : (N, 3) the pairs' flange translations (m)
    dm : (N, 3) their changes of ``(u, v, 1/s)``
    J : (3, 3) the image Jacobian fitted to them
    capture : :func:`capture_noise` of the same recording (its ``sd_px`` and ``n_eff``;
        NaN without repeated captures: then (N3) gives one capture's whole noise, reported
        as ``pose_sd_px``, and ``rms_touchup_um`` stays NaN: the adequacy test of
        :mod:`pipeline.stages.outliers.adequacy` stays untested, as before (on the truncated
        conformance sample the loop steps alone gave a ratio of 21, unexamined))
    s0 : designated long axis, px
    max_change_px : pairs whose predicted centre change exceeds this are left out
    min_pairs : fewer usable pairs leave the component unknown

    Returns
    -------
    dict (JSON-able): ``n_pose_pairs``, ``pose_sd_px`` (3,) the pose component's
    standard deviations of ``u, v, s``, ``cov_pose_flange_m2`` (3, 3), and
    ``rms_touchup_um`` ``sqrt(tr Sigma_touchup)`` of (N4) with ``rms_capture_um`` the
    repeated captures' share alone; figures NaN when unknown.
    """
    nan3 = [float("nan")] * 3
    out: dict[str, Any] = {
        "n_pose_pairs": 0,
        "pose_sd_px": nan3,
        "cov_pose_flange_m2": [nan3, nan3, nan3],
        "rms_capture_um": capture.get("rms_touchup_um", float("nan")),
        "rms_touchup_um": capture.get("rms_touchup_um", float("nan")),
    }
    J = np.asarray(J, dtype=float)
    if len(dF) == 0 or not np.all(np.isfinite(J)):
        return out
    pred = np.asarray(dF, dtype=float) @ J.T
    r = np.asarray(dm, dtype=float) - pred
    use = (np.hypot(pred[:, 0], pred[:, 1]) <= max_change_px) & np.all(np.isfinite(r), axis=1)
    if int(use.sum()) < min_pairs:
        return out
    r = r[use]
    sd = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
    sd_cap = np.asarray(capture.get("sd_px", nan3), dtype=float)
    var_cap = np.array([sd_cap[0] ** 2, sd_cap[1] ** 2, (sd_cap[2] / (s0 * s0)) ** 2])
    repeated = bool(np.all(np.isfinite(var_cap)))
    var_pose = np.maximum(sd**2 / 2.0 - (var_cap if repeated else 0.0), 0.0)
    Ji = np.linalg.inv(J)
    Sp = Ji @ np.diag(var_pose) @ Ji.T
    Sc = np.asarray(capture.get("cov_flange_m2"), dtype=float) / float(capture.get("n_eff", 1.0))
    total = Sp + Sc if repeated and np.all(np.isfinite(Sc)) else np.full((3, 3), np.nan)
    out.update(
        n_pose_pairs=int(use.sum()),
        pose_sd_px=[
            float(np.sqrt(var_pose[0])),
            float(np.sqrt(var_pose[1])),
            float(np.sqrt(var_pose[2])) * s0 * s0,
        ],
        cov_pose_flange_m2=Sp.tolist(),
        rms_touchup_um=float(1e6 * np.sqrt(np.trace(total))),
    )
    return out


def pin_offset_cov(noise: dict[str, Any] | None) -> list[list[float]] | None:
    """The pose component's covariance (m^2, flange frame) for (P1), or None.

    Only where the pose component was told apart from the repeated captures' noise
    (``rms_touchup_um`` finite): with one capture per touch-up, :func:`pose_noise`'s
    ``cov_pose_flange_m2`` holds one capture's whole noise, which averages over the
    touch-ups and is no pin offset (:func:`pipeline.estimation.uncertainty.with_pin_offset`).
    """
    if not noise or not math.isfinite(float(noise.get("rms_touchup_um", float("nan")))):
        return None
    cov = noise.get("cov_pose_flange_m2")
    a = np.asarray(cov, dtype=float) if cov is not None else np.full(1, np.nan)
    return (
        [list(map(float, row)) for row in a]
        if a.shape == (3, 3) and np.all(np.isfinite(a))
        else None
    )
