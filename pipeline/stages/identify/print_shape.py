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

The parameters ``theta = (kappa_1..kappa_{K-1}, c_0, s_0, .., c_{K-1}, s_{K-1})``
enter the fit (:func:`pipeline.stages.identify.stage`) through the correction: the
rows' ``d_i`` become ``d_i + g_i (B_i . theta)`` with ``B_i`` the design row of
(S2); a Gauss-Newton step on ``theta`` jointly with every other unknown,
repeated three times with ``alpha`` recomputed from the current kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.kinematics.se3 import F64

#: the touch-up columns of each touch-up's print-shape geometry: the lever ``g`` and the
#: long-axis direction ``l``, flange frame (``pipeline/measurement/image.py``, view_geometry)
SHAPE_COLUMNS = ("view_gx", "view_gy", "view_gz", "axis_lx", "axis_ly", "axis_lz")


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
    """

    theta: F64
    e1: F64
    e2: F64
    target_ids: tuple[int, ...]

    def lever_terms(self, R: F64, g: F64, l_flange: F64, target_id: np.ndarray) -> F64:
        """Each row's print correction ``eps_i g_i`` (S1), flange frame, (N, 3).

        Parameters
        ----------
        R : (N, 3, 3) the flange orientations ``R_base_flange`` of the fitted kinematics
        g, l_flange : (N, 3) the rows' levers and long-axis directions (flange frame)
        target_id : (N,) the rows' target ids; a row of a target the fit did not see,
            or without finite shape columns, gets zero
        """
        index = {t: k for k, t in enumerate(self.target_ids)}
        tk = np.array([index.get(int(t), -1) for t in target_id], dtype=int)
        seen = (tk >= 0) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(l_flange), axis=1)
        out = np.zeros((len(tk), 3))
        if not seen.any():
            return out
        l_base = np.einsum("nij,nj->ni", R[seen], l_flange[seen])
        B, _ = design_in_frames(l_base, tk[seen], self.e1, self.e2)
        out[seen] = g[seen] * (B @ self.theta)[:, None]
        return out
