"""The frame of the residual corrections: nominal against calibrated flange translations.

The touch-up stage measures its image Jacobian ``J`` from pairs of captures a small
pure flange translation apart, and each translation ``v_n`` is computed with the
*nominal* kinematics (``R_a^T (t_b - t_a)`` of the two nominal flange poses). The
arm moved by the true kinematics, so the translation that really happened is
``v = M(q) v_n``, with ``M`` a few thousandths off the identity (link-length and
axis errors). ``J`` then maps nominal translations to image changes, ``J = J_c M``
(``J_c`` the camera's own), and each correction ``d = -J^-1 e`` comes out in that
frame: ``d = M^-1 d_c``. Where the corrections are millimetres (a controller that
stopped short in size), a few thousandths of them is micrometres across the view,
far above a touch-up's noise there (~1 um), and it varies with the correction, so
no constant absorbs it. The fix: after a first fit, ``d_c = M_eff d`` with ``M_eff``
from the calibrated kinematics (:func:`translation_map`), then fit again
(:mod:`pipeline.stages.identify.stage`). ``M_eff`` is a pose average (F2) because ``J`` is
one matrix for every pose.

The maths. The image moves with the point of the flange at the target, the pin
``p`` (flange frame), not with the flange origin: a flange step of body twist
``(v, w)`` moves that point by ``v + w x p``. For a joint step ``dq`` the twist is
``Jb(q) dq``, ``Jb = diag(R^T, R^T) J_geo`` (:func:`pipeline.kinematics.chain.jacobian`,
base frame, rotated into the flange). A step the nominal robot computes as the pure
translation ``(v_n, 0)`` is ``dq = Jb_n(q)^+ (v_n, 0)`` (minimum-norm for a redundant
arm); the calibrated robot turns it into ``(A_vv v_n, A_wv v_n)`` with
``A = Jb_c(q) Jb_n(q)^+``, so the pin point moves by

    M(q) v_n,      M(q) = A_vv - [p]_x A_wv                                  (F1)

The second term is not small: a step the nominal robot keeps pure turns the true
flange by ~1e-4 rad per 8 mm (simulated standard cell), which at a 0.25 m pin is
~5 mrad of the step.

``J`` is the least-squares fit over every pair ``p`` of ``dm_p = J_c M(q_p) v_p``
(``v_p`` its nominal translation), so it holds ``J = J_c M_eff`` with the pairs'
scatter-weighted mean

    M_eff = (sum_p M(q_p) v_p v_p^T) (sum_p v_p v_p^T)^-1
          ~ (sum_i M(q_i) S_i) (sum_i S_i)^-1,      S_i = sum_{p in i} v_p v_p^T    (F2)

the pairs of touch-up ``i`` being taken within millimetres of its final pose
``q_i``; the touch-up table carries ``S_i`` (:data:`PAIR_COLUMNS`). ``M(q)`` varies
from pose to pose by as much as its mean differs from the identity, and the pairs'
directions differ between touch-ups, so the plain mean of ``M(q_i)`` can be ~1 mrad
from ``M_eff`` where (F2) is within 0.05 mrad of the pairs' own fit (simulated
standard cell). The correction in the calibrated flange frame is then
``d_c = M_eff d``. Without ``S_i`` (a table from another writer) the plain weighted
mean is used.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.kinematics.chain import Chain, fk, jacobian
from pipeline.kinematics.se3 import F64, skew

#: condition number of the nominal body Jacobian above which a pose is left out
SINGULAR_COND = 1e4
#: the touch-up table's columns of ``S_i`` (F2): the scatter ``sum v v^T`` of the
#: nominal flange translations of the image-Jacobian pairs taken during touch-up ``i``, m^2
PAIR_COLUMNS = ("pair_sxx", "pair_syy", "pair_szz", "pair_sxy", "pair_sxz", "pair_syz")
_PAIR_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


#: largest ``|M_eff - I|`` entry applied: a robot whose nominal model moves the flange
#: 5 % off its true motion is not one a touch-up calibration starts from, so a larger
#: map comes from kinematics the poses do not determine (measured: 0.35 on a weakly
#: excited synthetic table, cond 5e4) and is not applied
MAX_FRAME_DEVIATION = 0.05


def frame_deviation(M: F64) -> float:
    """Largest ``|M - I|`` entry; above :data:`MAX_FRAME_DEVIATION` the map is not applied."""
    return float(np.abs(np.asarray(M, dtype=float) - np.eye(3)).max())


def table_scatters(df: pd.DataFrame) -> F64 | None:
    """Every row's pair scatter ``(M, 3, 3)`` from a table's :data:`PAIR_COLUMNS` (NaN
    where not a number), None when the table lacks them (another writer's)."""
    if not all(c in df.columns for c in PAIR_COLUMNS):
        return None
    cols = [pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float) for c in PAIR_COLUMNS]
    return scatter_from_columns(np.stack(cols, axis=1))


def scatter_columns(S: F64) -> dict[str, F64]:
    """``(N, 3, 3)`` scatters -> the six :data:`PAIR_COLUMNS` arrays, ``(N,)`` each."""
    return {c: np.asarray(S[:, i, j]) for c, (i, j) in zip(PAIR_COLUMNS, _PAIR_INDEX, strict=True)}


def scatter_from_columns(values: F64) -> F64:
    """``(N, 6)`` in :data:`PAIR_COLUMNS` order -> ``(N, 3, 3)`` symmetric scatters."""
    v = np.asarray(values, dtype=float)
    S = np.zeros((len(v), 3, 3))
    for k, (i, j) in enumerate(_PAIR_INDEX):
        S[:, i, j] = v[:, k]
        S[:, j, i] = v[:, k]
    return S


def body_jacobian(chain: Chain, q: F64) -> F64:
    """Flange-frame (body) Jacobian of the flange origin, ``(N, 6, n)``: rows ``v, w``."""
    J = jacobian(chain, q)
    R = fk(chain, q)[:, :3, :3]
    Rt = np.transpose(R, (0, 2, 1))
    return np.concatenate([Rt @ J[:, :3], Rt @ J[:, 3:]], axis=1)


def translation_map(
    nominal: Chain,
    calibrated: Chain,
    q: F64,
    w: F64 | None = None,
    S: F64 | None = None,
    p_point: F64 | None = None,
) -> F64:
    """Nominal flange translations -> calibrated ones: ``M_eff`` of (F2), or a mean of (F1).

    Parameters
    ----------
    nominal, calibrated : chains base -> flange (same joints)
    q : (N, n) joint vectors of the poses
    w : (N,) weights of the plain mean (default equal); ignored with ``S``
    S : (N, 3, 3) pair scatters ``S_i`` (F2), optional
    p_point : (3,) the flange point whose translation is mapped, the pin (default origin)

    Returns
    -------
    (3, 3) ``M_eff`` (the identity for identical chains). Poses within
    ``1 / SINGULAR_COND`` of a singularity (condition number of ``Jb_n`` above it)
    are left out: there a small flange translation is not a small joint step; so are
    poses with a joint that is not a number. The identity when every pose is.
    """
    q2 = np.atleast_2d(np.asarray(q, dtype=float))
    Jn = body_jacobian(nominal, q2)
    Jc = body_jacobian(calibrated, q2)
    ww = np.ones(len(q2)) if w is None else np.asarray(w, dtype=float)
    # a pose with a missing joint (a row identification does not use) has no Jacobian
    fin = np.all(np.isfinite(Jn), axis=(1, 2)) & np.all(np.isfinite(Jc), axis=(1, 2))
    cond = np.full(len(q2), np.inf)
    cond[fin] = np.linalg.cond(Jn[fin])
    ok = (cond < SINGULAR_COND) & (ww > 0)
    px = skew(np.zeros(3) if p_point is None else p_point)

    def per_pose(sel: np.ndarray) -> F64:
        A = Jc[sel] @ np.linalg.pinv(Jn[sel])
        return np.asarray(A[:, :3, :3] - px @ A[:, 3:, :3])

    if S is not None:
        Sa = np.asarray(S, dtype=float)
        ok &= np.all(np.isfinite(Sa), axis=(1, 2))
        if ok.any() and np.linalg.cond(Sa[ok].sum(axis=0)) < 1e8:
            return np.asarray(
                np.einsum("nij,njk->ik", per_pose(ok), Sa[ok]) @ np.linalg.inv(Sa[ok].sum(0))
            )
    if not ok.any():
        return np.eye(3)
    return np.asarray(np.einsum("n,nij->ij", ww[ok], per_pose(ok)) / ww[ok].sum())
