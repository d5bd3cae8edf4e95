"""Targets that are not perfect circles: each target's printed size and out-of-roundness.

A touch-up drives the image long axis to the designated ``s0``. A printed disc
whose extent along the image's long axis is ``(1 + eps)`` times the nominal
diameter therefore stops the camera ``z eps`` too far (``s = f D / z``, ``z``
the stand-off), and the point that touched the target is

    p_i = T_base_flange(q_i) (p_pin + d_i + eps_i g_i),      g_i = z r_z      (S1)

(``g`` per touch-up from the image Jacobian:
:func:`pipeline.measurement.image.view_geometry`). For a print whose boundary is
``r(psi) = R (1 + e cos 2 (psi - phi))`` (semi-axes ``R (1 +- e)``, long axis at
``phi`` in the plate) and a relative size error ``kappa``, the extent along a
line at angle ``alpha`` in the plate is ``2 R (1 + kappa + e cos 2 (alpha - phi))``
to first order, so with ``c = e cos 2 phi``, ``s = e sin 2 phi``

    eps_i = kappa_t + c_t cos 2 alpha_i + s_t sin 2 alpha_i                (S2)

``alpha_i`` the angle of touch-up ``i``'s image long axis in target ``t``'s plate.
A tilted view puts the long axis along the plate line perpendicular to the tilt;
a face-on one along the print's own long axis, where (S2) gives
``kappa + e``, as it should. The plate frame: the long-axis directions
``l_i`` (flange frame, from the touch-up table) turned into the base frame by
the current kinematics lie in the plate plane (the image plane meets it along
them), so the plate normal ``n_t`` is the direction most nearly perpendicular
to all of them (smallest eigenvector of ``sum l l^T``), ``(e1, e2)`` complete it
and ``alpha_i = atan2(l_i . e2, l_i . e1)``.

What is identifiable: the roll dependence ``(c_t, s_t)`` of every target needs
touch-ups whose long axes turn through the plate; the size ``kappa_t`` only
relative to one reference target (the first): a size error common to every
print moves every touch-up by the same ``z kappa`` along the view, which is the
virtual pin's own along-view coordinate. It is held at zero and named.

(S2) is first order in the ellipticity *against the tilt*: it holds where the
view's tilt sets the long axis (``theta_v^2 / 2 >> 2 e``, ``theta_v`` the angle
between the view and the plate normal). Near face-on, where tilt and print
compete for the long axis, it does not. To first order in both, the image
ellipse's shape is ``I + v`` (semi-axes ``R (1 - theta_v^2 / 4 +- |v| / 2)``)
with the anisotropy, as a 2-vector of angle ``2 alpha`` in the plate,

    v = 2 p - (theta_v^2 / 2) u(2 tau),     p = (c, s) = e u(2 phi)

(``u(x) = (cos x, sin x)``, ``tau`` the tilt's direction in the plate), so the
long axis is ``R (1 + |v| / 2 - theta_v^2 / 4)`` and, with
``theta_v^2 / 2 = |v - 2 p|`` from the same equation,

    eps_i = kappa_t + (|v_i| - |v_i - 2 p_t|) / 2                          (S3)

``v_i`` is measured: the image's own anisotropy ``2 (s - s_minor) / (s + s_minor)``
along ``u(2 alpha_i)`` (the touch-up table's ``axis_anisotropy``). Where tilt
dominates, ``|v_i - 2 p| = |v_i| - 2 p . u(2 alpha_i)`` to first order and (S3) is
(S2); face-on (``v_i = 2 p``) it gives ``kappa + e``; in between it holds where
(S2) errs by up to ``e`` (a UR5e-like cell at 240 mm with 60 um out-of-round
prints viewed within 8 deg of face-on: 0.34 mm shape error with (S2)). Rows
without the anisotropy column (tables written elsewhere) use (S2).

The parameters ``theta = (kappa_1..kappa_{K-1}, c_0, s_0, .., c_{K-1}, s_{K-1})``
enter the fit (:func:`pipeline.stages.identify.stage`) through the correction: the
rows' ``d_i`` become ``d_i + g_i eps_i(theta)``; a Gauss-Newton step on ``theta``
(its Jacobian rows ``B_i = d eps_i / d theta``: (S2)'s rows at ``p = 0``) jointly
with every other unknown, repeated three times with ``alpha`` recomputed from the
current kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.kinematics.se3 import F64

#: the touch-up columns of each touch-up's print-shape geometry: the lever ``g`` and the
#: long-axis direction ``l``, flange frame (``pipeline/measurement/image.py``, view_geometry)
SHAPE_COLUMNS = ("view_gx", "view_gy", "view_gz", "axis_lx", "axis_ly", "axis_lz")
#: the optional column of the image's anisotropy ``|v_i|`` of (S3); without it, (S2)
ANISOTROPY_COLUMN = "axis_anisotropy"
#: ``|v - 2 p|`` is smoothed as ``sqrt(|v - 2 p|^2 + MIN_MISS^2)``: where the print alone
#: sets the long axis its direction turns fast; eps moves by at most ``MIN_MISS / 2``
MIN_MISS = 2e-5


def plate_frames(
    l_base: F64, tk: np.ndarray, K: int, view_base: F64 | None = None
) -> tuple[F64, F64, F64]:
    """Per target the plate normal and in-plane axes from the long-axis directions.

    The normal faces the cameras (``n . v < 0`` summed over the views ``v``) when
    ``view_base`` is given, else its largest component is positive; ``e1`` (the most
    common long-axis direction) has its largest component positive, ``e2 = n x e1``.
    So the frame, and the orientation angle measured in it, does not flip with the
    sign an eigen-solver happens to return.

    Parameters
    ----------
    l_base : (N, 3) unit long-axis directions in the base frame
    tk : (N,) target index of each row
    K : number of targets
    view_base : (N, 3) the cameras' view directions in the base frame, optional

    Returns
    -------
    n, e1, e2 : (K, 3) each (NaN for a target without two distinct directions)
    """
    n = np.full((K, 3), np.nan)
    e1 = np.full((K, 3), np.nan)
    e2 = np.full((K, 3), np.nan)
    for t in range(K):
        L = l_base[(tk == t) & np.all(np.isfinite(l_base), axis=1)]
        if len(L) < 2:
            continue
        lam, V = np.linalg.eigh(L.T @ L)
        if lam[1] < 1e-6 * lam[2]:  # every long axis along one line: no plane
            continue
        nt = V[:, 0]
        a = V[:, 2]  # the most common long-axis direction, in the plane
        if view_base is not None:
            if float(np.sum(view_base[tk == t] @ nt)) > 0:
                nt = -nt
        elif nt[np.argmax(np.abs(nt))] < 0:
            nt = -nt
        if a[np.argmax(np.abs(a))] < 0:
            a = -a
        n[t], e1[t], e2[t] = nt, a, np.cross(nt, a)
    return n, e1, e2


def design(
    l_base: F64, tk: np.ndarray, K: int, view_base: F64 | None = None
) -> tuple[F64, np.ndarray]:
    """Design rows ``B`` (N, 3K - 1) of (S2) and which rows can use them.

    Columns: ``kappa_1 .. kappa_{K-1}`` (target 0 is the size reference), then
    ``c_t, s_t`` per target. Rows of a target without a plate frame get zeros.
    ``view_base`` as in :func:`plate_frames`.

    Returns
    -------
    B : (N, 3K - 1) ; ok : (N,) bool
    """
    _, e1, e2 = plate_frames(l_base, tk, K, view_base)
    return design_in_frames(l_base, tk, e1, e2)


def design_in_frames(l_base: F64, tk: np.ndarray, e1: F64, e2: F64) -> tuple[F64, np.ndarray]:
    """Design rows ``B`` (N, 3K - 1) of (S2) in given plate frames ``e1, e2`` (K, 3).

    :func:`design` with the frames of :func:`plate_frames` passed in, so that rows the
    frames were not computed from (touch-ups held out of a fit) are placed in the
    frames of the fit. Rows whose target has no frame (NaN) get zeros.
    """
    N, K = len(tk), len(e1)
    B = np.zeros((N, 3 * K - 1))
    ok = np.all(np.isfinite(l_base), axis=1) & np.all(np.isfinite(e1[tk]), axis=1)
    a = np.arctan2(np.einsum("ni,ni->n", l_base, e2[tk]), np.einsum("ni,ni->n", l_base, e1[tk]))
    rows = np.flatnonzero(ok)
    for i in rows:
        t = int(tk[i])
        if t > 0:
            B[i, t - 1] = 1.0
        B[i, K - 1 + 2 * t] = np.cos(2.0 * a[i])
        B[i, K + 2 * t] = np.sin(2.0 * a[i])
    return B, ok


def print_error(B: F64, tk: np.ndarray, K: int, theta: F64, v_mag: F64 | None) -> tuple[F64, F64]:
    """Each row's relative long-axis error ``eps_i`` by (S3) and its Jacobian in ``theta``.

    Parameters
    ----------
    B : (N, 3K - 1) the rows' (S2) design (:func:`design_in_frames`): ``u(2 alpha_i)`` in
        the columns of its target's ``(c, s)``, zeros for rows without a frame
    tk : (N,) target index of each row
    K : number of targets
    theta : (3K - 1,) the print parameters
    v_mag : (N,) the rows' measured anisotropy ``|v_i|``; None, or NaN on a row: (S2)

    Returns
    -------
    eps : (N,) ; J : (N, 3K - 1) ``d eps / d theta`` (``B`` itself on (S2) rows)
    """
    eps = B @ theta
    J = B.copy()
    if v_mag is None:
        return eps, J
    N = len(tk)
    ci = K - 1 + 2 * np.asarray(tk, dtype=int)
    ui = np.stack([B[np.arange(N), ci], B[np.arange(N), ci + 1]], axis=1)  # u(2 alpha_i)
    rows = np.flatnonzero(np.isfinite(v_mag) & (np.abs(ui).sum(axis=1) > 0))
    if not len(rows):
        return eps, J
    p = np.stack([theta[ci[rows]], theta[ci[rows] + 1]], axis=1)
    v = v_mag[rows, None] * ui[rows]
    w = v - 2.0 * p
    nw = np.sqrt(np.sum(w * w, axis=1) + MIN_MISS**2)
    kap = np.where(tk[rows] > 0, theta[np.maximum(tk[rows] - 1, 0)], 0.0)
    eps[rows] = kap + 0.5 * (v_mag[rows] - nw)
    J[rows, ci[rows]] = w[:, 0] / nw
    J[rows, ci[rows] + 1] = w[:, 1] / nw
    return eps, J


def summarise(theta: F64, std: F64, K: int, diameter_m: float | None) -> list[dict[str, float]]:
    """Per target: size error and out-of-roundness from ``theta`` (and their standard errors).

    ``kappa`` (relative, target 0 = 0 by definition), ``e = sqrt(c^2 + s^2)``, the long
    axis' angle ``phi = atan2(s, c) / 2`` in the plate frame of :func:`plate_frames`, and
    with ``diameter_m`` the diameter error ``kappa D`` and the difference of the printed
    diameters ``2 e D`` (um).
    """
    out = []
    for t in range(K):
        kap = float(theta[t - 1]) if t > 0 else 0.0
        kap_sd = float(std[t - 1]) if t > 0 else 0.0
        c, s = float(theta[K - 1 + 2 * t]), float(theta[K + 2 * t])
        sc, ss = float(std[K - 1 + 2 * t]), float(std[K + 2 * t])
        e = float(np.hypot(c, s))
        row = {
            "target": float(t),
            "kappa": kap,
            "kappa_std": kap_sd,
            "ellipticity": e,
            "ellipticity_std": float(np.hypot(sc, ss) / np.sqrt(2.0)),
            "orientation_rad": float(0.5 * np.arctan2(s, c)),
        }
        if diameter_m:
            row["diameter_error_um"] = 1e6 * kap * diameter_m
            row["out_of_round_um"] = 1e6 * 2.0 * e * diameter_m
        out.append(row)
    return out


@dataclass(frozen=True)
class ShapeFit:
    """A fitted print shape, enough to correct touch-ups the fit has not seen.

    Attributes
    ----------
    theta : (3K - 1,) the parameters of (S2): ``kappa_1 .. kappa_{K-1}``, ``c_t, s_t``
    e1, e2 : (K, 3) each target's in-plane axes (base frame of the fitted kinematics,
        :func:`plate_frames` of the fit's rows)
    target_ids : the touch-up table's target id of each of the K targets
    anisotropic : the shape was fitted with (S3); held-out rows are corrected the same way
    """

    theta: F64
    e1: F64
    e2: F64
    target_ids: tuple[int, ...]
    #: fitted with (S3) (the rows' anisotropy read), else (S2)
    anisotropic: bool = False

    def lever_terms(
        self,
        R: F64,
        g: F64,
        l_flange: F64,
        target_id: np.ndarray,
        v_mag: F64 | None = None,
    ) -> F64:
        """Each row's print correction ``eps_i g_i`` (S1), flange frame, (N, 3).

        Parameters
        ----------
        R : (N, 3, 3) the flange orientations ``R_base_flange`` of the fitted kinematics
        g, l_flange : (N, 3) the rows' levers and long-axis directions (flange frame)
        target_id : (N,) the rows' target ids; a row of a target the fit did not see,
            or without finite shape columns, gets zero
        v_mag : (N,) the rows' image anisotropy of (S3); None: (S2)
        """
        index = {t: k for k, t in enumerate(self.target_ids)}
        tk = np.array([index.get(int(t), -1) for t in target_id], dtype=int)
        seen = (tk >= 0) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(l_flange), axis=1)
        out = np.zeros((len(tk), 3))
        if not seen.any():
            return out
        l_base = np.einsum("nij,nj->ni", R[seen], l_flange[seen])
        B, _ = design_in_frames(l_base, tk[seen], self.e1, self.e2)
        vm = None if v_mag is None or not self.anisotropic else np.asarray(v_mag, dtype=float)[seen]
        eps, _ = print_error(B, tk[seen], len(self.e1), self.theta, vm)
        out[seen] = g[seen] * eps[:, None]
        return out
