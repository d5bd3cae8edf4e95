"""Identification: from converged touch-ups to a calibrated robot.

Measurement model (one row ``i`` per converged touch-up of target ``k``)::

    T_base_flange(q_i; x) @ (p_flange_pin + d_i) = p_base_target[k]          (1)

with ``x`` the error model's kinematic corrections (:mod:`pipeline.models`),
``p_flange_pin`` the virtual pin, ``d_i`` the residual correction
``(dx, dy, dz)_flange`` of the touch-up (``../shared/spec/touchups.md``) and
every target position unknown. A known distance ``D`` between targets ``A``
and ``B`` adds the residual ``w_D (|p_A - p_B| - D)`` with a strong weight
``w_D``. Rows are weighted by ``sqrt(weight)``.

Solver: Levenberg-Marquardt (MINPACK through ``scipy.optimize.least_squares``;
TRF when a robust loss is asked for) with the analytic Jacobian of (1):
``d/dx`` from the model, ``d/dp_pin = R_base_flange``, ``d/dp_target = -I``.
Parameters are scaled by ``ErrorModel.column_scale`` (radians by the working radius ``L``, ``x_scale = 1/L``)
so a radian and the metre it moves the pin by weigh alike. The pin and targets
start from the exact linear least-squares solution of (1) at nominal kinematics.

Noise model: a touch-up's error is fixed in the flange (camera) frame and far
larger along the view than across it. After an isotropic fit the residuals'
3x3 covariance in the flange frame is estimated and the fit repeated with the
residuals whitened, ``W R_i^T (p_i - t_k)`` (feasible generalised least
squares; ``noise_model="isotropic"`` skips it).

Identifiability: redundancies are exact only where residuals vanish, so they
are found on exact synthetic touch-ups of the nominal robot (cached per robot
and model): the scaled kinematic columns, with the pin and target columns
projected out, go through a QR factorisation with column pivoting (Businger &
Golub 1965; the base-parameter method of Gautier & Khalil 1990 / Hollerbach &
Wampler 1996). Columns whose pivot is below ``rank_tol`` times the largest are
held at nominal and named with a reason: absorbed by the targets or the pin
(base frame, pin against the last joint) or redundant with named identified
parameters. Without a known distance the uniform scale is held by a gauge row
``v . x = 0`` (``v`` the model direction of a uniform scale). A second pivoted
QR on the actual touch-ups (``data_tol``) holds what these poses fail to excite.

Uncertainty: ``cov = sigma^2 (J^T J)^-1`` over the estimated unknowns with
``sigma^2 = |r|^2 / (m - p)``; standard errors, the correlation matrix, and the
pin position error the covariance predicts over poses spread through the
touched volume (``sqrt(mean trace(J_w cov J_w^T))``). A covariance sees only
random error: systematic input errors are invisible to it.

Observability indices O1..O5 (:mod:`pipeline.models.observability`) of the
reduced Jacobian are recorded with its condition number.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd
import scipy.linalg
from scipy.optimize import least_squares

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.evaluate import workspace_poses
from pipeline.kinematics.chain import Chain, load_chain
from pipeline.kinematics.se3 import F64
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.models import make_model, model_names
from pipeline.models.base import ErrorModel
from pipeline.models.observability import indices_from_singular_values, project_out
from pipeline.stages.print_shape import SHAPE_COLUMNS

DEFAULT_MODEL = "full"
#: ``model="auto"`` tries these in order and keeps the first the touch-ups support
AUTO_ORDER = ("full", "offsets")


class TooFewTouchups(CalibrationFailed):
    """The touch-ups leave no redundancy for the model's identifiable parameters."""


@dataclass
class IdentifyConfig:
    """Identification settings.

    Attributes
    ----------
    model : error model name (``full``, ``mdh``, ``poe``, ``offsets``, ``elastic``), ``all`` (fit each), or
        ``auto`` (``full`` if the touch-ups suffice, else ``offsets``; the summary says which)
    distances : known distances ``(label A, label B, metres)`` between targets
    robust_loss : ``scipy.optimize.least_squares`` loss (``linear``, ``soft_l1``, ``huber``, ``cauchy``, ...)
    f_scale : soft threshold of a robust loss, metres of pin residual
    distance_weight : weight of a known-distance residual relative to a touch-up row
    rank_tol : relative pivot threshold below which a parameter is structurally unidentifiable
    data_tol : relative pivot threshold below which these touch-ups do not excite a parameter
    noise_model : ``flange`` (estimate the pin error's 3x3 covariance in the flange frame from
        the residuals and refit whitened: a touch-up is far less precise along the view than
        across it) or ``isotropic``
    max_nfev : iteration budget of the solver
    n_workspace : poses over which the predicted error is evaluated
    seed : seed of those poses
    target_shape : the targets' print shape (:mod:`pipeline.stages.print_shape`): ``auto`` fits
        each target's size (relative to the first) and out-of-roundness when the table has
        the shape columns and every target ``shape_min_touchups`` touch-ups, and keeps them
        when an F-test at ``shape_alpha`` finds them significant; ``fit`` keeps them whenever
        they can be fitted; ``none`` never fits them
    shape_alpha, shape_min_touchups : see ``target_shape``. ``shape_alpha = 1e-4``: a
        run fits up to four models with two tests each, so about ``1e-3`` per run
        (Bonferroni). At ``1e-3`` a linear-image UR5e-like cell with perfect prints was
        fitted at p = 7.6e-4 and lost 5 % of shape accuracy; 20 um out-of-round prints
        give p ~ 1e-34.
    target_diameter_m : printed diameter, to state print errors in micrometres (else relative)
    implied_target_diameter_m : the diameter the touch-up stage's image Jacobian implies
        (:func:`pipeline.stages.touchup.diameter_from_jacobian`), checked against
        ``target_diameter_m`` by the guardrails; None for a table without images
    accept_implausible : identify even where :mod:`pipeline.stages.plausibility` finds an
        input the nominal robot contradicts (joint values outside the URDF's limits, a
        known distance off by more than the nominal robot's own error); the lines are
        then kept in the summary as ``implausible``
    check_plausibility : run those guardrails at all; False for refits on a subset of
        touch-ups whose full table passed them (cross-validation), ``implausible`` then []
    strict_distances : a known distance naming a target absent from the table is bad input
        (``vtcal identify``); False drops it with a note (``vtcal run``: the recording's
        metadata names every target of the cell, a truncated run may not have reached them all)
    """

    model: str = "auto"
    distances: list[tuple[int | str, int | str, float]] = field(default_factory=list)
    robust_loss: str = "linear"
    f_scale: float = 1e-4
    distance_weight: float = 100.0
    rank_tol: float = 1e-8
    data_tol: float = 1e-6
    noise_model: str = "flange"
    reweight_passes: int = 1
    max_nfev: int = 200
    n_workspace: int = 200
    seed: int = 0
    strict_distances: bool = True
    target_shape: str = "auto"
    shape_alpha: float = 1e-4
    shape_min_touchups: int = 6
    target_diameter_m: float | None = None
    implied_target_diameter_m: float | None = None
    accept_implausible: bool = False
    check_plausibility: bool = True


@dataclass
class IdentifyResult:
    """Everything identification produces for one error model.

    Attributes
    ----------
    model : error model name
    parameters, residuals, targets : artefact tables (``schemas/NAME.json``)
    calibrated_urdf : nominal URDF with the corrections in its joint origins and the virtual pin
    summary : JSON-able figures (see :func:`identify`)
    chain : calibrated chain, base link to flange link
    p_flange_pin : (3,) identified virtual pin, flange frame
    x : (P,) model parameters (held ones 0)
    error_model : the fitted model: ``error_model.pin_and_jacobian(x, q, pin)`` predicts
        the pin exactly, also where ``chain`` (the URDF's rigid kinematics) cannot
        (a model with ``urdf_exact = False``)
    """

    model: str
    parameters: pd.DataFrame
    residuals: pd.DataFrame
    targets: pd.DataFrame
    calibrated_urdf: str
    summary: dict[str, Any]
    chain: Chain
    p_flange_pin: F64
    x: F64 = field(repr=False, default_factory=lambda: np.zeros(0))
    error_model: ErrorModel | None = field(repr=False, default=None)

    def predict(self, q: F64, d: F64) -> F64:
        """Pin positions ``T_base_flange(q_i; x) (p_pin + d_i)`` of the fitted model, (N, 3)."""
        pts = self.p_flange_pin[None, :] + d
        if self.error_model is not None:
            p, _, _ = self.error_model.pin_and_jacobian(self.x, q, pts, jac=False)
            return p
        from pipeline.kinematics.chain import fk

        T = fk(self.chain, q)
        return np.asarray(np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3])


# ----------------------------------------------------------------------------- input


@dataclass
class _Data:
    """The rows that enter the fit, and bookkeeping for every input row."""

    q: F64  # (N, n) used rows
    d: F64  # (N, 3)
    sw: F64  # (N,) sqrt weights
    tk: np.ndarray  # (N,) target index 0..K-1 among used targets
    K: int
    target_ids: list[int]  # per used target index
    target_labels: list[str]
    dist: list[tuple[int, int, float]]  # (target index A, B, metres)
    dropped_distances: list[str]
    rows: (
        pd.DataFrame
    )  # every input row: touchup_id, target_id, target_label, used, reason, weight, q...
    used_idx: np.ndarray  # positions of used rows in ``rows``
    q_all: F64  # (M, n) all rows (NaN where missing)
    d_all: F64
    tk_all: np.ndarray  # target index per row (-1 if target not used)
    #: (N, 3) each used row's print-size lever ``g`` and (N, 3) long-axis direction ``l``
    #: (flange frame, :mod:`pipeline.stages.print_shape`), None without those columns
    shape_g: F64 | None = None
    shape_l: F64 | None = None


def _prepare(touchups: pd.DataFrame, chain: Chain, config: IdentifyConfig) -> _Data:
    df = touchups.reset_index(drop=True)
    names = chain.joint_names
    missing = [c for c in ("touchup_id", "target_id", *names) if c not in df.columns]
    if missing:
        raise BadInput(
            f"touch-up table: missing column(s) {missing} (joints of the chain: {names}; "
            f"columns: {list(df.columns)})"
        )
    df = _numeric_columns(df, names)
    M = len(df)
    q_all = df[names].to_numpy(dtype=float)
    d_all = np.zeros((M, 3))
    for i, c in enumerate(("dx_flange", "dy_flange", "dz_flange")):
        if c in df.columns:
            d_all[:, i] = df[c].to_numpy(dtype=float)
    w = df["weight"].to_numpy(dtype=float) if "weight" in df.columns else np.ones(M)
    reason = [[] for _ in range(M)]  # type: list[list[str]]
    if "converged" in df.columns:
        for i in np.flatnonzero(~df["converged"].fillna(False).to_numpy(dtype=bool)).tolist():
            reason[i].append("not converged")
    if "inlier" in df.columns:
        rej = df["reason"].astype(str).to_numpy() if "reason" in df.columns else None
        for i in np.flatnonzero(~df["inlier"].fillna(False).to_numpy(dtype=bool)).tolist():
            extra = f" ({rej[i]})" if rej is not None and rej[i] not in ("", "nan", "None") else ""
            reason[i].append("rejected as outlier" + extra)
    for i in np.flatnonzero(~(w > 0)).tolist():
        reason[i].append("weight not positive")
    for i in np.flatnonzero(w > MAX_WEIGHT).tolist():
        reason[i].append(f"weight above {MAX_WEIGHT:g}")
    for i in np.flatnonzero(~np.all(np.isfinite(q_all), axis=1)).tolist():
        reason[i].append("joint position missing")
    for i in np.flatnonzero(np.any(np.abs(q_all) > MAX_JOINT, axis=1)).tolist():
        reason[i].append(f"joint position beyond {MAX_JOINT:g}")
    for i in np.flatnonzero(~np.all(np.isfinite(d_all), axis=1)).tolist():
        reason[i].append("correction missing")
        d_all[i] = 0.0
    for i in np.flatnonzero(np.any(np.abs(d_all) > MAX_CORRECTION_M, axis=1)).tolist():
        reason[i].append(f"correction beyond {MAX_CORRECTION_M:g} m")
        d_all[i] = 0.0
    used = np.array([not r for r in reason], dtype=bool)

    raw_labels = df["target_id"].tolist()
    order: list[Any] = []
    for lab in raw_labels:
        if lab not in order and not (isinstance(lab, float) and math.isnan(lab)):
            order.append(lab)
    all_int = all(
        isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer()) for v in order
    )
    tid_of = {lab: (int(lab) if all_int else i) for i, lab in enumerate(order)}
    row_tid = np.array([tid_of.get(lab, -1) for lab in raw_labels], dtype=np.int64)
    row_label = [str(int(lab)) if all_int and lab in tid_of else str(lab) for lab in raw_labels]
    for i in np.flatnonzero(row_tid < 0).tolist():
        reason[i].append("no target label")
        used[i] = False

    used_labels = [lab for lab in order if np.any(used & (row_tid == tid_of[lab]))]
    k_of = {tid_of[lab]: k for k, lab in enumerate(used_labels)}
    tk_all = np.array([k_of.get(int(t), -1) for t in row_tid], dtype=np.int64)
    label_text = [str(int(lab)) if all_int else str(lab) for lab in used_labels]
    all_text = {(str(int(lab)) if all_int else str(lab)) for lab in order}

    dist: list[tuple[int, int, float]] = []
    dropped: list[str] = []
    for a, b, metres in config.distances:
        sa, sb = str(a), str(b)
        absent = [s for s in (sa, sb) if s not in all_text]
        if absent and config.strict_distances:
            raise BadInput(
                f"known distance {a}:{b}={metres}: no target {absent[0]!r} in the touch-up table "
                f"(targets: {sorted(all_text)})"
            )
        if absent:
            dropped.append(f"{a}:{b}={metres} (no target {absent[0]!r} in the touch-ups)")
            continue
        if sa == sb or not metres > 0:
            raise BadInput(f"known distance {a}:{b}={metres}: needs two targets and metres > 0")
        if sa in label_text and sb in label_text:
            dist.append((label_text.index(sa), label_text.index(sb), float(metres)))
        else:
            dropped.append(f"{a}:{b}={metres} (a target has no usable touch-up)")

    rows = pd.DataFrame(
        {
            "touchup_id": df["touchup_id"].to_numpy(dtype=np.int64),
            "target_id": row_tid,
            "target_label": row_label,
            "used": used,
            "reason": ["; ".join(r) for r in reason],
            "weight": np.where(np.isfinite(w), w, 0.0),
        }
    )
    ui = np.flatnonzero(used)
    shape_g = shape_l = None
    if all(c in df.columns for c in SHAPE_COLUMNS):
        sh = np.stack(
            [pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float) for c in SHAPE_COLUMNS],
            axis=1,
        )[ui]
        if len(sh) and np.all(np.isfinite(sh)):
            shape_g, shape_l = sh[:, :3], sh[:, 3:]
    return _Data(
        q=q_all[ui],
        d=d_all[ui],
        sw=np.sqrt(w[ui]),
        tk=tk_all[ui],
        K=len(used_labels),
        target_ids=[tid_of[lab] for lab in used_labels],
        target_labels=label_text,
        dist=dist,
        dropped_distances=dropped,
        rows=rows,
        used_idx=ui,
        q_all=q_all,
        d_all=d_all,
        tk_all=tk_all,
        shape_g=shape_g,
        shape_l=shape_l,
    )


#: rows beyond these are flagged, not fitted: a joint at 1000 rad (or m), a residual correction
#: of a metre or a relative weight of a million is a corrupt value, not a measurement
MAX_JOINT = 1e3
MAX_CORRECTION_M = 1.0
MAX_WEIGHT = 1e6


def _numeric_columns(df: pd.DataFrame, names: list[str]) -> pd.DataFrame:
    """The table with its numeric columns as numbers; one-line BadInput for any that is not.

    ``touchup_id`` must be unique integers; joint, correction and weight columns
    floats (empty cells are NaN and flag their row later).
    """
    dup_cols = sorted({str(c) for c in df.columns[df.columns.duplicated()]})
    if dup_cols:
        raise BadInput(f"touch-up table: column(s) {dup_cols} appear more than once")
    converted: dict[str, pd.Series] = {}
    for c in [*names, "dx_flange", "dy_flange", "dz_flange", "weight", "touchup_id"]:
        if c not in df.columns:
            continue
        col = df[c]
        if c != "touchup_id" and col.dtype == np.float64:
            continue  # already what is needed: no copy (this runs on every identify call)
        if not (pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col)):
            num = pd.to_numeric(col, errors="coerce")
            bad = num.isna() & col.notna()
            if bad.any():
                i = int(np.flatnonzero(bad.to_numpy())[0])
                raise BadInput(
                    f"touch-up table: column {c!r} row {i}: {col.iloc[i]!r} is not a number"
                )
            col = num
        if c != "touchup_id":
            converted[c] = col.astype(float)
    if converted:
        df = df.assign(**converted)
    tid = pd.to_numeric(df["touchup_id"], errors="coerce").to_numpy(dtype=float)
    bad_id = ~np.isfinite(tid) | (tid != np.round(tid))
    if bad_id.any():
        i = int(np.flatnonzero(bad_id)[0])
        raise BadInput(
            f"touch-up table: column 'touchup_id' row {i}: {df['touchup_id'].iloc[i]!r} is not "
            "an integer"
        )
    if df["touchup_id"].dtype != np.int64:
        df = df.assign(touchup_id=tid.astype(np.int64))
    dup = df["touchup_id"].duplicated()
    if dup.any():
        i = int(np.flatnonzero(dup.to_numpy())[0])
        raise BadInput(
            f"touch-up table: touchup_id {int(df['touchup_id'].iloc[i])} appears more than once "
            f"(row {i}); it must be unique per row"
        )
    return df


def _implausible(
    chain: Chain,
    data: _Data,
    touchups: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    config: IdentifyConfig,
) -> list[str]:
    """The guardrails of :mod:`pipeline.stages.plausibility` on the used touch-ups."""
    from pipeline.kinematics.urdf import parse_urdf
    from pipeline.stages import plausibility as pl

    limits = pl.joint_values(data.q, chain)
    robot = parse_urdf(urdf)
    used = touchups.reset_index(drop=True).iloc[data.used_idx]
    values = {  # the table's columns of URDF joints outside the chain
        c: pd.to_numeric(used[c], errors="coerce").to_numpy(dtype=float)
        for c in used.columns
        if c in robot.joints and c not in chain.joint_names
    }
    lines = limits + pl.joints_outside_chain(values, robot, base_link, flange_link)
    if data.K >= 1 and len(data.q) >= 2:  # one nominal fit serves both checks
        _, tg, rho = pl.nominal_targets(chain, data.q, data.d, data.tk, data.K, data.sw)
        if not limits:  # joints outside their limits already explain a bad nominal fit
            lines += pl.nominal_fit(rho)
        lines += pl.known_distances(tg, rho, data.dist, data.target_labels)
    return lines + pl.target_diameter(config.target_diameter_m, config.implied_target_diameter_m)


def _refuse_early(data: _Data, source_rows: int) -> None:
    N = len(data.q)
    if N == 0:
        why = pd.Series(
            [r for rs in data.rows["reason"] for r in str(rs).split("; ") if r], dtype=object
        ).value_counts()
        because = ", ".join(f"{n} {r}" for r, n in why.items()) or "none converged"
        raise CalibrationFailed(
            f"no usable touch-ups ({source_rows} rows; {because}): add converged touch-ups"
        )
    if data.K < 2 and not data.dist:
        raise CalibrationFailed(
            f"all {N} usable touch-ups are of a single target ({data.target_labels[0]}) and no "
            "known distance is given: touch up at least one more target (and give a known "
            "distance with --distance A:B=METRES for absolute accuracy)"
        )
    if N < 2 or float(np.ptp(data.q, axis=0).max()) < 1e-6:
        raise CalibrationFailed(
            f"all {N} usable touch-ups have the same joint vector: add touch-ups at different "
            "arm orientations around each target"
        )


# ----------------------------------------------------------------------------- problem


class _Problem:
    """Residuals (1) and their analytic Jacobian over ``z = [x_free, pin, targets]``."""

    def __init__(
        self,
        model: ErrorModel,
        data: _Data,
        config: IdentifyConfig,
        gauge: F64 | None = None,
    ) -> None:
        self.model = model
        self.data = data
        self.P = model.n_params
        self.wd = float(config.distance_weight)
        self.N = len(data.q)
        self.gauge = gauge  # (P,) row of the scale-gauge constraint gauge @ x = 0, or None
        self.m = 3 * self.N + len(data.dist) + (gauge is not None)
        self.free = np.arange(self.P)
        # (3, 3) whitening of the pin residual in the flange frame, or None (isotropic)
        self.W: F64 | None = None

    # z layout helpers
    def split(self, z: F64) -> tuple[F64, F64, F64]:
        nf = len(self.free)
        x = np.zeros(self.P)
        x[self.free] = z[:nf]
        return x, z[nf : nf + 3], z[nf + 3 :].reshape(self.data.K, 3)

    def join(self, x: F64, pin: F64, targets: F64) -> F64:
        return np.concatenate([x[self.free], pin, targets.ravel()])

    def full_eval(self, x: F64, pin: F64, targets: F64, jac: bool = True) -> tuple[F64, F64 | None]:
        """Residual (m,) and Jacobian (m, P + 3 + 3K) over all model parameters."""
        D = self.data
        pts = pin + D.d
        p, R, Jx = self.model.pin_and_jacobian(x, D.q, pts, jac=jac)
        e = (p - targets[D.tk]) * D.sw[:, None]
        M = None
        if self.W is not None:  # whitened: W R_i^T (p_i - t_k)
            M = np.einsum("ab,ncb->nac", self.W, R)
            e = np.einsum("nab,nb->na", M, e)
        r = np.empty(self.m)
        r[: 3 * self.N] = e.ravel()
        for j, (a, b, dm) in enumerate(D.dist):
            r[3 * self.N + j] = self.wd * (np.linalg.norm(targets[a] - targets[b]) - dm)
        if self.gauge is not None:
            r[-1] = self.wd * float(self.gauge @ x)
        if not jac:
            return r, None
        assert Jx is not None
        ncol = self.P + 3 + 3 * D.K
        J = np.zeros((self.m, ncol))
        sw = D.sw[:, None, None]
        rows = np.arange(3 * self.N).reshape(self.N, 3)
        if M is None:
            J[: 3 * self.N, : self.P] = (Jx * sw).reshape(3 * self.N, self.P)
            J[: 3 * self.N, self.P : self.P + 3] = (R * sw).reshape(3 * self.N, 3)
            for c in range(3):
                J[rows[:, c], self.P + 3 + 3 * D.tk + c] = -D.sw
        else:
            Msw = M * sw
            J[: 3 * self.N, : self.P] = (Msw @ Jx).reshape(3 * self.N, self.P)
            J[: 3 * self.N, self.P : self.P + 3] = (Msw @ R).reshape(3 * self.N, 3)
            for c in range(3):
                J[rows, (self.P + 3 + 3 * D.tk + c)[:, None]] = -Msw[:, :, c]
        for j, (a, b, _) in enumerate(D.dist):
            u = targets[a] - targets[b]
            u = u / max(np.linalg.norm(u), 1e-12)
            J[3 * self.N + j, self.P + 3 + 3 * a : self.P + 6 + 3 * a] = self.wd * u
            J[3 * self.N + j, self.P + 3 + 3 * b : self.P + 6 + 3 * b] = -self.wd * u
        if self.gauge is not None:
            J[-1, : self.P] = self.wd * self.gauge
        return r, J

    def columns(self) -> np.ndarray:
        """Columns of the full Jacobian that ``z`` covers."""
        return np.concatenate([self.free, np.arange(self.P, self.P + 3 + 3 * self.data.K)])

    def fun(self, z: F64) -> F64:
        # the Jacobian comes almost free with the residual and MINPACK asks for it at
        # the point it just evaluated (accepted steps): compute both, keep the last
        r, J = self.full_eval(*self.split(z))
        assert J is not None
        self._last = (z.tobytes(), J)
        return r

    def jac(self, z: F64) -> F64:
        last = getattr(self, "_last", None)
        if last is not None and last[0] == z.tobytes():
            J = last[1]
        else:
            J = self.full_eval(*self.split(z))[1]
            assert J is not None
        return J[:, self.columns()]


def _initial_pin_targets(model: ErrorModel, data: _Data, x: F64) -> tuple[F64, F64]:
    """Exact linear least squares of (1) for the pin and targets at fixed kinematics."""
    N, K = len(data.q), data.K
    p0, R, _ = model.pin_and_jacobian(x, data.q, data.d, jac=False)
    A = np.zeros((3 * N, 3 + 3 * K))
    A[:, :3] = R.reshape(3 * N, 3)
    rows = np.arange(3 * N).reshape(N, 3)
    for c in range(3):
        A[rows[:, c], 3 + 3 * data.tk + c] = -1.0
    b = -p0.ravel()
    sw = np.repeat(data.sw, 3)
    sol = np.asarray(np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)[0], dtype=np.float64)
    pin: F64 = sol[:3]
    targets: F64 = sol[3:].reshape(K, 3)
    return pin, targets


@dataclass(frozen=True)
class _Structure:
    """What a model can identify from touch-ups of this robot at all."""

    kept: np.ndarray  # columns identified, sorted
    held: dict[int, str]  # column -> reason
    gauge: F64 | None  # (P,) scale-gauge row (scaled units), None if the scale is identified
    length: float  # characteristic length of the scaling the gauge was built in


@lru_cache(maxsize=64)
def _structure(
    name: str, urdf: str, base_link: str, flange_link: str, has_dist: bool, tol: float
) -> _Structure:
    """Structural identifiability from exact synthetic touch-ups of the nominal robot.

    Redundancies are exact only where the residuals vanish (a base rotation turns
    a residual vector; a uniform scale shrinks it), so they are found on exact
    touch-ups of the nominal robot: 3 targets x 15 poses spread over the joint
    ranges, with a known distance, the Jacobian (scaled, pin and targets
    projected out) through a pivoted QR. Without a known distance one more
    direction is unidentifiable, the uniform scale: the model-parameter
    direction ``v`` that, with the pin and targets, scales every pin position
    (least squares of ``J_x v + J_pin w = p``). It is held by the gauge
    constraint ``v . x_scaled = 0`` (the fit has no component along the scale
    of the nominal robot) instead of holding one arbitrary length. Cached per
    robot and model.
    """
    from pipeline.evaluate import synthetic_touchups

    chain = load_chain(urdf, base_link, flange_link)
    model = make_model(name, chain)
    rng = np.random.default_rng(20240601)
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    p_c = np.array([0.013, -0.009, 0.15])
    # well-spread exact touch-ups: around the zero pose, else around mid-range
    for centre in (np.clip(0.0, lo, hi), 0.5 * (lo + hi)):
        table, tg = synthetic_touchups(
            chain, p_c, 3, 15, rng, q_centre=centre, centre_spread_rad=0.8
        )
        if len(table) >= 36 and table["target_id"].nunique() == 3:
            break
    if len(table) < 12 or table["target_id"].nunique() < 2:
        raise CalibrationFailed(
            f"model {name}: cannot place exact touch-ups on the nominal robot "
            f"{base_link} -> {flange_link} to rate identifiability (joint limits too tight?)"
        )
    data = _prepare(table, chain, IdentifyConfig(distances=[(0, 1, 1.0)]))
    prob = _Problem(model, data, IdentifyConfig(distance_weight=1.0))
    P = model.n_params
    _, J = prob.full_eval(model.zero(), p_c, tg)
    assert J is not None
    Lc = float(np.sqrt(np.mean(np.sum(tg**2, axis=1))))
    pscale = model.column_scale(Lc)
    prio = model.param_priority
    A = project_out(J[:, :P] * pscale, J[:, P:])
    kept, held, _ = _select(A * prio, tol)
    reasons = _held_reasons(A, kept, held, model.param_names, tol)
    gauge = None
    if not has_dist:
        # scale: the direction that leaves every touch-up row unchanged but stretches the
        # distance between targets 0 and 1 (J_x v + J_pin w + J_t u = 0, d|t0 - t1| = 1)
        N = len(data.q)
        B = np.concatenate([J[:, kept] * pscale[kept], J[:, P:]], axis=1)
        rhs = np.zeros(B.shape[0])
        rhs[3 * N] = 1.0
        sol = np.linalg.lstsq(B, rhs, rcond=None)[0]
        fit = np.linalg.norm(B @ sol - rhs)
        v = sol[: len(kept)]
        if fit < 1e-6 and np.linalg.norm(v) > 0:
            gauge = np.zeros(P)
            gauge[kept] = v / np.linalg.norm(v)
    return _Structure(kept=kept, held=reasons, gauge=gauge, length=Lc)


def _select(A: F64, tol: float) -> tuple[np.ndarray, np.ndarray, F64]:
    """Pivoted QR of the reduced, scaled Jacobian: kept (sorted) and held columns, |R_ii|."""
    if A.shape[1] == 0:
        return np.arange(0), np.arange(0), np.zeros(0)
    _, R, piv = scipy.linalg.qr(A, mode="economic", pivoting=True)
    rd = np.abs(np.diag(R))
    if rd.size == 0 or rd[0] == 0:
        return np.arange(0), np.asarray(piv), rd
    rank = int(np.sum(rd > tol * rd[0]))
    return np.sort(piv[:rank]), np.asarray(piv[rank:]), rd


def _held_reasons(
    A: F64, kept: np.ndarray, held: np.ndarray, names: list[str], tol: float
) -> dict[int, str]:
    """A one-line reason for each held column (see module docstring)."""
    out: dict[int, str] = {}
    norms = np.linalg.norm(A, axis=0)
    big = norms.max() if norms.size else 1.0
    Ak = A[:, kept]
    for j in held:
        j = int(j)
        if norms[j] <= max(tol, 1e-9) * big:
            out[j] = (
                "moves the pin as the target positions or the virtual pin do (base frame, "
                "pin offset): absorbed by them"
            )
            continue
        c = np.linalg.lstsq(Ak, A[:, j], rcond=None)[0] if kept.size else np.zeros(0)
        top = np.argsort(-np.abs(c))[:3]
        deps = ", ".join(names[int(kept[t])] for t in top if abs(c[t]) > 1e-6)
        out[j] = f"redundant with identified parameters ({deps})" if deps else "not identifiable"
    return out


def _flange_whitening(prob: _Problem, z: F64, n_free: int) -> tuple[F64 | None, F64 | None]:
    """Whitening matrix of the pin residual in the flange frame, from the current fit.

    ``e_i = R_i^T (p_i - t_k)`` over the used rows; ``S = cov(e) m / (m - p)``
    (weighted, centred: a constant flange-frame offset is the pin's). The returned
    ``W = s S^(-1/2)`` (eigenvalues floored at 1e-4 of the largest) keeps residuals
    in metres (``s^2`` is the mean variance). None when the residuals vanish
    (exact data) or fewer than 15 residual degrees of freedom remain.

    Returns
    -------
    W : (3, 3) or None
    sigma : (3,) standard deviations along the principal flange-frame axes, m
    """
    D = prob.data
    x, pin, tg = prob.split(z)
    p, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    e = np.einsum("nji,nj->ni", R, p - tg[D.tk])
    w = D.sw**2
    mu = (w[:, None] * e).sum(axis=0) / w.sum()
    c = e - mu
    dof = 3 * len(e) - (n_free + 3 + 3 * D.K)
    if dof < 15:  # a 3x3 covariance from fewer residual degrees of freedom is noise
        return None, None
    S = (w[:, None, None] * c[:, :, None] * c[:, None, :]).sum(axis=0) / w.sum()
    S *= 3 * len(e) / dof
    lam, V = np.linalg.eigh(S)
    if lam.max() < (1e-9) ** 2:  # exact data: nothing to weigh
        return None, None
    lam = np.maximum(lam, lam.max() * 1e-4)
    s = np.sqrt(lam.mean())
    W = s * (V / np.sqrt(lam)) @ V.T
    return W, np.sqrt(lam)


def _fit_print_shape(
    prob: _Problem, sol: Any, solve: Any, config: IdentifyConfig, n_free: int
) -> tuple[Any, _Data, dict[str, Any]]:
    """Each target's print size and out-of-roundness, solved jointly with the fit.

    :mod:`pipeline.stages.print_shape` has the model (S1)-(S2). Three Gauss-Newton
    steps on ``theta`` together with every unknown of ``prob`` (the design ``B`` is
    recomputed from the current kinematics before each), each followed by the full
    solve from where it stood; the rows' corrections become ``d_i + g_i (B_i . theta)``.
    ``auto`` keeps the result when the nested-model F-test on the unwhitened residual
    sums rejects ``theta = 0`` at ``shape_alpha``. Else it tries the relative sizes
    alone (``kappa``, ``K - 1`` parameters: a per-target constant along the view, which
    is also what a per-target error of the image Jacobian's size row leaves after a
    large residual correction) with the same test. Otherwise the fit is the one before.

    Returns
    -------
    sol : the solver result to continue with
    data : the data it belongs to (a copy with the corrected ``d``, or ``prob.data``)
    summary : ``fitted``, ``note``, F-test figures, per-target figures
    """
    import dataclasses

    from scipy.stats import f as f_dist

    from pipeline.stages import print_shape as ps

    D0 = prob.data
    K, N = D0.K, len(D0.q)
    counts = np.bincount(D0.tk, minlength=K)
    if int(counts.min()) < config.shape_min_touchups:
        return (
            sol,
            D0,
            {
                "fitted": False,
                "note": f"print shape not fitted: a target has {int(counts.min())} touch-ups "
                f"(needs {config.shape_min_touchups})",
            },
        )
    assert D0.shape_g is not None and D0.shape_l is not None
    n_all = 3 * K - 1

    def rss(D: _Data, z: F64) -> float:
        x, pin, tg = prob.split(z)
        p, _, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
        return float(np.sum(((p - tg[D.tk]) * D.sw[:, None]) ** 2))

    rss0 = rss(D0, sol.x)
    sol0, W0 = sol, prob.W
    G: F64 = D0.shape_g
    L: F64 = D0.shape_l

    def attempt(cols: np.ndarray) -> tuple[Any, _Data, dict[str, Any], bool]:
        """Fit the ``theta`` columns ``cols``; (sol, data, summary, significant)."""
        ne = len(cols)
        dof1 = 3 * N + len(D0.dist) - (n_free + 3 + 3 * K) - ne
        if dof1 < 5:
            return (
                sol0,
                D0,
                {"fitted": False, "note": "print shape not fitted: too few touch-ups"},
                False,
            )
        D = dataclasses.replace(D0, d=D0.d.copy(), d_all=D0.d_all.copy())
        prob.data, prob.W = D, W0
        theta = np.zeros(n_all)

        def joint(z: F64) -> tuple[F64, F64, F64]:
            """(A, r, B): Jacobian over [z, theta[cols]], residual and the design at ``z``."""
            x, pin, tg = prob.split(z)
            r, Jf = prob.full_eval(x, pin, tg)
            assert Jf is not None
            _, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
            B, _ = ps.design(np.einsum("nij,nj->ni", R, L), D.tk, K, np.einsum("nij,nj->ni", R, G))
            V = np.einsum("nij,nj->ni", R, G) if prob.W is None else G @ prob.W.T
            Bc = B[:, cols]
            S = np.zeros((prob.m, ne))
            S[: 3 * N] = (V[:, :, None] * Bc[:, None, :] * D.sw[:, None, None]).reshape(3 * N, ne)
            return np.hstack([Jf[:, prob.columns()], S]), r, B

        s1 = sol0
        for _ in range(3):
            A, r, B = joint(s1.x)
            cn = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
            step = np.linalg.lstsq(A / cn, -r, rcond=None)[0] / cn
            theta[cols] += step[-ne:]
            D.d[:] = D0.d + G * (B @ theta)[:, None]
            D.d_all[D.used_idx] = D.d
            s1 = solve(s1.x)
        A, r, B = joint(s1.x)
        cn = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
        dof_w = prob.m - A.shape[1]
        sig2 = float(r @ r / dof_w) if dof_w > 0 else float("nan")
        _, sv, Vt = np.linalg.svd(A / cn, full_matrices=False)
        good = sv > sv[0] * 1e-12
        cov = (Vt[good].T / sv[good] ** 2) @ Vt[good] * sig2
        std = np.full(n_all, np.nan)
        std[cols] = np.sqrt(np.clip(np.diag(cov)[-ne:], 0, None)) / cn[-ne:]
        rss1 = rss(D, s1.x)
        F = ((rss0 - rss1) / ne) / max(rss1 / dof1, 1e-300)
        p_value = float(f_dist.sf(F, ne, dof1)) if rss1 > 0 else 0.0
        what = "print shape" if ne == n_all else "relative print sizes"
        out: dict[str, Any] = {
            "fitted": False,
            "parameters": "size and out-of-roundness" if ne == n_all else "size",
            "F": float(F),
            "p_value": p_value,
            "alpha": config.shape_alpha,
            "rss_before_mm2": 1e6 * rss0,
            "rss_after_mm2": 1e6 * rss1,
            "n_params": ne,
            "held": "the size of target 0's print (the reference): a size error common to "
            "every print moves every touch-up along the view like the virtual pin's own "
            "coordinate",
            "targets": ps.summarise(theta, std, K, config.target_diameter_m),
            "note": f"{what} fitted ({ne} parameters, F = {F:.1f}, p = {p_value:.2g})",
        }
        if ne < n_all:  # sizes only: the out-of-roundness was not fitted, not zero
            for t in out["targets"]:
                for k in ("ellipticity", "ellipticity_std", "orientation_rad", "out_of_round_um"):
                    if k in t:
                        t[k] = float("nan")
        return s1, D, out, p_value < config.shape_alpha

    # the whole print model, then the relative sizes alone (K - 1 parameters: a per-target
    # constant along the view, which is also what a per-target error of the image
    # Jacobian's size row leaves after the residual correction); the first significant
    # one is kept (two tests at shape_alpha each)
    tries = [np.arange(n_all)] + ([np.arange(K - 1)] if K > 1 else [])
    tried: list[dict[str, Any]] = []
    for i, cols in enumerate(tries):
        s1, D1, out, significant = attempt(cols)
        tried.append(out)
        if significant or (config.target_shape == "fit" and i == 0 and "F" in out):
            out["fitted"] = True
            out["tried"] = [{k: t.get(k) for k in ("parameters", "F", "p_value")} for t in tried]
            return s1, D1, out
    prob.data, prob.W = D0, W0
    first = tried[0]
    if "F" not in first:
        return sol0, D0, first
    first["tried"] = [{k: t.get(k) for k in ("parameters", "F", "p_value")} for t in tried]
    first["note"] = (
        "print shape not significant ("
        + "; ".join(
            f"{t['parameters']}: F = {t['F']:.2f}, p = {t['p_value']:.2g}"
            for t in tried
            if "F" in t
        )
        + f" >= {config.shape_alpha:g}): perfect circles of one size assumed"
    )
    for t in first["targets"]:
        for k in t:
            if k != "target":
                t[k] = float("nan")
    return sol0, D0, first


def _partial_loss(name: str, n_robust: int) -> Any:
    """A ``least_squares`` loss callable: ``name`` on the first ``n_robust`` residuals
    (the touch-up rows), linear on the rest (known distances, scale gauge), so a
    robust loss never weakens a constraint.

    ``rho(z)`` with ``z = f^2`` (Triggs et al. 2000): soft_l1 ``2(sqrt(1+z)-1)``,
    huber ``z`` or ``2 sqrt(z) - 1``, cauchy ``ln(1+z)``, arctan ``arctan(z)``.
    """
    if name not in ("soft_l1", "huber", "cauchy", "arctan"):
        raise BadInput(f"robust loss {name!r}: use linear, soft_l1, huber, cauchy or arctan")

    def loss(z: F64) -> F64:
        out = np.empty((3, z.size))
        out[0], out[1], out[2] = z, 1.0, 0.0
        a = z[:n_robust]
        if name == "soft_l1":
            t = 1.0 + a
            out[0, :n_robust] = 2.0 * (np.sqrt(t) - 1.0)
            out[1, :n_robust] = t**-0.5
            out[2, :n_robust] = -0.5 * t**-1.5
        elif name == "huber":
            big = a > 1.0
            sa = np.sqrt(np.where(big, a, 1.0))
            out[0, :n_robust] = np.where(big, 2.0 * sa - 1.0, a)
            out[1, :n_robust] = np.where(big, 1.0 / sa, 1.0)
            out[2, :n_robust] = np.where(big, -0.5 / sa**3, 0.0)
        elif name == "cauchy":
            t = 1.0 + a
            out[0, :n_robust] = np.log1p(a)
            out[1, :n_robust] = 1.0 / t
            out[2, :n_robust] = -1.0 / t**2
        else:
            t = 1.0 + a**2
            out[0, :n_robust] = np.arctan(a)
            out[1, :n_robust] = 1.0 / t
            out[2, :n_robust] = -2.0 * a / t**2
        return out

    return loss


def predicted_errors(Jw: F64, cov: F64, p: F64, kind: str) -> F64:
    """Per-pose standard pin error the covariance predicts after a registration.

    The error field ``dp = J_w dz`` (``J_w`` (N, 3, p), ``dz ~ N(0, cov)``) minus its
    best-fit rigid (``absolute``) or similarity (``shape``) motion: to first
    order a projection ``Pr = I - Q Q^T`` onto the complement of the fields
    ``[I, -[p_i]x]`` (and ``p_i - mean`` for a similarity). Returns
    ``sqrt(trace_i(Pr J cov J^T Pr))`` per pose, (N,).
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
    var = np.einsum("ij,jk,ik->i", G, cov, G).reshape(N, 3).sum(axis=1)
    return np.asarray(np.sqrt(np.clip(var, 0.0, None)))


# ----------------------------------------------------------------------------- main


def identify(
    touchups: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    config: IdentifyConfig | None = None,
) -> IdentifyResult | dict[str, IdentifyResult]:
    """Identify kinematic corrections, the virtual pin and the targets from touch-ups.

    Parameters
    ----------
    touchups : DataFrame
        A touch-up table (``../shared/spec/touchups.md``; the touchups and
        inliers artefacts are ones). Rows used: ``converged`` (if the column
        exists), ``inlier`` (if it exists), ``weight > 0`` and finite joints.
    urdf : nominal URDF XML
    base_link, flange_link : the chain (``flange_link`` may be a tool link; its
        fixed joints stay nominal and the pin is found in its frame)
    config : IdentifyConfig

    Returns
    -------
    IdentifyResult, or ``{model name: IdentifyResult}`` for ``model="all"``.

    Raises
    ------
    BadInput
        Missing joint columns, unknown model, a distance naming an unknown target.
    CalibrationFailed
        No usable touch-ups, a single target without a known distance, all
        poses identical, or too few touch-ups for the model (says how many to add).
    """
    config = config or IdentifyConfig()
    chain = load_chain(urdf, base_link, flange_link)
    data = _prepare(touchups, chain, config)
    _refuse_early(data, len(touchups))
    implausible = (
        _implausible(chain, data, touchups, urdf, base_link, flange_link, config)
        if config.check_plausibility
        else []
    )
    if implausible and not config.accept_implausible:
        raise CalibrationFailed(
            "implausible input: "
            + "; ".join(implausible)
            + " (rerun with --accept-implausible if it is right)"
        )
    if config.model == "all":
        results: dict[str, IdentifyResult] = {}
        errors: list[str] = []
        for name in model_names():
            try:
                results[name] = _identify_one(name, chain, data, urdf, flange_link, config)
            except (BadInput, CalibrationFailed) as exc:
                errors.append(f"{name}: {exc}")
        if not results:
            raise CalibrationFailed("no error model could be identified: " + " | ".join(errors))
        for r in results.values():
            r.summary["other_models_failed"] = errors
            r.summary["implausible"] = implausible
        return results
    if config.model == "auto":
        refusals: list[str] = []
        for name in AUTO_ORDER:
            try:
                res = _identify_one(name, chain, data, urdf, flange_link, config)
            except TooFewTouchups as exc:
                refusals.append(str(exc))
                continue
            res.summary["model_choice"] = f"auto: {name}" + (
                f" (fell back: {'; '.join(refusals)})" if refusals else ""
            )
            if refusals:
                res.summary["headline"].insert(1, f"model auto -> {name}: " + refusals[0])
            res.summary["implausible"] = implausible
            return res
        raise TooFewTouchups(" | ".join(refusals))
    one = _identify_one(config.model, chain, data, urdf, flange_link, config)
    one.summary["implausible"] = implausible
    return one


def _identify_one(
    name: str,
    chain: Chain,
    data: _Data,
    urdf: str,
    flange_link: str,
    config: IdentifyConfig,
) -> IdentifyResult:
    t0 = time.perf_counter()
    try:
        model = make_model(name, chain)
    except KeyError as exc:
        raise BadInput(f"--model {name!r}: {exc.args[0]}") from exc
    x0 = model.zero()
    pin0, tg0 = _initial_pin_targets(model, data, x0)
    prob = _Problem(model, data, config)
    P, K, N = model.n_params, data.K, len(data.q)

    # -- scaling and identifiability
    Lc = float(max(np.sqrt(np.mean(np.sum(tg0**2, axis=1))), 0.1))
    pscale = model.column_scale(Lc)  # column scale: J[:, j] * pscale[j]
    st = _structure(
        name, urdf, chain.base_link, chain.tip_link, bool(data.dist), float(config.rank_tol)
    )
    if st.gauge is not None:
        # the gauge row is defined in the structure's scaling; x_scaled = x * pscale
        g = st.gauge * model.column_scale(st.length)
        prob = _Problem(model, data, config, gauge=g / np.linalg.norm(g))
    r0, J0 = prob.full_eval(x0, pin0, tg0)
    e0 = r0[: 3 * N].reshape(N, 3) / data.sw[:, None]
    initial_rms = float(np.sqrt(np.mean(np.sum(e0**2, axis=1))))
    assert J0 is not None
    Jn0 = J0[:, P:]
    reasons = dict(st.held)
    r_struct = len(st.kept)
    nuis_rank = int(np.linalg.matrix_rank(Jn0))
    rows_avail = prob.m - nuis_rank
    if rows_avail < r_struct + 3:
        need = math.ceil((r_struct + 3 - rows_avail) / 3)
        raise TooFewTouchups(
            f"model {name}: {N} usable touch-ups on {K} targets give {prob.m} equations; the "
            f"targets and the pin take {nuis_rank}, leaving {rows_avail} for the {r_struct} "
            f"kinematic parameters it identifies: add at least {need} more touch-up"
            + ("s" if need > 1 else "")
            + (" (or use --model offsets)" if name != "offsets" else "")
        )
    # what these touch-ups fail to excite among the structurally identifiable columns
    A = project_out(J0[:, st.kept] * pscale[st.kept], Jn0)
    k_loc, h_loc, _ = _select(A, config.data_tol)
    kept = st.kept[k_loc]
    for j in st.kept[h_loc]:
        reasons[int(j)] = "not excited by these touch-ups (add poses that vary this joint)"
    held = np.array(sorted(reasons), dtype=np.int64)
    prob.free = kept

    # -- solve
    z0 = prob.join(x0, pin0, tg0)
    xs = np.concatenate([1.0 / pscale[kept], np.ones(3 + 3 * K)])
    linear = config.robust_loss == "linear"

    def solve(z_start: F64) -> Any:
        return least_squares(
            prob.fun,
            z_start,
            jac=prob.jac,
            method="lm" if linear and prob.m >= z0.size else "trf",
            loss=config.robust_loss if linear else _partial_loss(config.robust_loss, 3 * N),
            f_scale=config.f_scale,
            x_scale=xs,
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            max_nfev=config.max_nfev,
        )

    sol = solve(z0)
    noise_note = "isotropic pin residuals in the base frame"
    sigma_flange = None
    if config.noise_model == "flange":
        # feasible generalised least squares: the touch-up error lives in the flange
        # (camera) frame, far larger along the view than across it; estimate its 3x3
        # covariance from the residuals and refit with them whitened.
        for _ in range(config.reweight_passes):
            W, sigma_flange = _flange_whitening(prob, sol.x, len(kept))
            if W is None:
                break
            prob.W = W
            sol = solve(sol.x)
        if prob.W is not None:
            noise_note = (
                "pin residuals whitened by their covariance in the flange frame, estimated from "
                "the fit (feasible generalised least squares)"
            )
    shape: dict[str, Any] | None = None
    if data.shape_g is not None and config.target_shape != "none":
        sol, data, shape = _fit_print_shape(prob, sol, solve, config, len(kept))
    x, pin, tg = prob.split(sol.x)
    r, Jfull = prob.full_eval(x, pin, tg)
    assert Jfull is not None

    # -- uncertainty
    cols = prob.columns()
    Jz = Jfull[:, cols]
    zscale = np.concatenate([pscale[kept], np.ones(3 + 3 * K)])
    U, s, Vt = np.linalg.svd(Jz * zscale, full_matrices=False)
    dof = prob.m - Jz.shape[1]
    sigma2 = float(r @ r / dof) if dof > 0 else float("nan")
    good = s > s[0] * 1e-12
    Vs = Vt[good].T / s[good]
    cov = (zscale[:, None] * (Vs @ Vs.T)) * zscale[None, :] * sigma2
    std_z = np.sqrt(np.clip(np.diag(cov), 0, None))
    ne = len(kept) + 3
    cov_e = cov[:ne, :ne]
    de = np.sqrt(np.clip(np.diag(cov_e), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_e / np.outer(de, de)
    Ared = project_out(Jfull[:, :P][:, kept] * pscale[kept], Jfull[:, P:])
    obs = indices_from_singular_values(np.linalg.svd(Ared, compute_uv=False), prob.m)

    rng = np.random.default_rng(config.seed)
    q_ws = workspace_poses(data.q, config.n_workspace, rng)
    pw, Rw, Jw = model.pin_and_jacobian(x, q_ws, pin, jac=True)
    assert Jw is not None
    Jwe = np.concatenate([Jw[:, :, kept], Rw], axis=2)
    pred = {kind: predicted_errors(Jwe, cov_e, pw, kind) for kind in ("shape", "absolute", "raw")}

    # -- tables
    calibrated = model.chain(x)
    # the pin-to-target distances themselves (residuals.parquet's), not the whitened
    # residual vector the solver minimised: a fit residual in millimetres means a distance
    p_used, _, _ = model.pin_and_jacobian(x, data.q, pin + data.d, jac=False)
    e_used = p_used - tg[data.tk]
    norms_used = np.linalg.norm(e_used, axis=1)
    wsum = float(np.sum(data.sw**2))
    rms = float(np.sqrt(np.sum(norms_used**2 * data.sw**2) / wsum))
    est_index = -np.ones(P, dtype=np.int64)
    est_index[kept] = np.arange(len(kept))
    nominal_vals = model.param_nominal
    prow = []
    for j in range(P):
        i = int(est_index[j])
        prow.append(
            {
                "model": name,
                "name": model.param_names[j],
                "kind": "kinematic",
                "joint": model.param_joints[j],
                "unit": model.param_units[j],
                "nominal": float(nominal_vals[j]),
                "value": float(x[j]),
                "std": float(std_z[i]) if i >= 0 and dof > 0 else float("nan"),
                "identifiable": i >= 0,
                "held_reason": "" if i >= 0 else reasons.get(j, "not identifiable"),
                "estimated_index": i,
                "correlation": list(map(float, corr[i])) if i >= 0 else [],
            }
        )
    for c, axis in enumerate("xyz"):
        i = len(kept) + c
        prow.append(
            {
                "model": name,
                "name": f"pin.{axis}",
                "kind": "pin",
                "joint": "",
                "unit": "m",
                "nominal": float(pin0[c]),
                "value": float(pin[c]),
                "std": float(std_z[i]) if dof > 0 else float("nan"),
                "identifiable": True,
                "held_reason": "",
                "estimated_index": i,
                "correlation": list(map(float, corr[i])),
            }
        )
    parameters = pd.DataFrame(prow)

    rows = data.rows.copy()
    M = len(rows)
    res = np.full((M, 3), np.nan)
    pos = np.full((M, 3), np.nan)
    ok = np.all(np.isfinite(data.q_all), axis=1)
    if ok.any():
        pa, _, _ = model.pin_and_jacobian(x, data.q_all[ok], pin + data.d_all[ok], jac=False)
        pos[ok] = pa
        has_t = ok & (data.tk_all >= 0)
        res[has_t] = pos[has_t] - tg[data.tk_all[has_t]]
    residuals = pd.DataFrame(
        {
            "model": name,
            "touchup_id": rows["touchup_id"],
            "target_id": rows["target_id"],
            "target_label": rows["target_label"],
            "used": rows["used"],
            "reason": rows["reason"],
            "weight": rows["weight"],
            "rx": res[:, 0],
            "ry": res[:, 1],
            "rz": res[:, 2],
            "norm": np.linalg.norm(res, axis=1),
            "px": pos[:, 0],
            "py": pos[:, 1],
            "pz": pos[:, 2],
        }
    )
    tstd = std_z[len(kept) + 3 :].reshape(K, 3) if dof > 0 else np.full((K, 3), np.nan)
    targets = pd.DataFrame(
        {
            "model": name,
            "target_id": np.array(data.target_ids, dtype=np.int64),
            "target_label": data.target_labels,
            "x": tg[:, 0],
            "y": tg[:, 1],
            "z": tg[:, 2],
            "std_x": tstd[:, 0],
            "std_y": tstd[:, 1],
            "std_z": tstd[:, 2],
            "n_touchups": np.bincount(data.tk, minlength=K).astype(np.int64),
        }
    )
    fitted = shape is not None and bool(shape.get("fitted"))
    for key in ("kappa", "ellipticity", "orientation_rad", "diameter_error_um", "out_of_round_um"):
        vals = [t.get(key, np.nan) for t in shape["targets"]] if fitted and shape else [np.nan] * K
        targets[f"print_{key}"] = np.asarray(vals, dtype=float)
    urdf_out = write_calibrated_urdf(urdf, model.origins(x), flange_link, pin)

    scale_held = not data.dist
    held_list = [
        {"name": model.param_names[int(j)], "reason": reasons.get(int(j), "")} for j in held
    ]
    seconds = time.perf_counter() - t0
    summary: dict[str, Any] = {
        "print_shape": shape,
        "model": name,
        "model_description": model.description,
        "n_rows": int(M),
        "n_used": int(N),
        "n_targets": int(K),
        "n_params": int(P),
        "n_identified": int(len(kept)),
        "n_structural": int(r_struct),
        "unidentifiable": [h["name"] for h in held_list],
        "held": held_list,
        "scale_held": scale_held,
        "scale_note": (
            "no known distance: the length scale was not identifiable and was held at the "
            "nominal model's; only shape accuracy applies"
            if scale_held
            else f"length scale identified from {len(data.dist)} known distance(s)"
        ),
        "base_note": "the base frame against the targets is held at nominal (never identifiable)",
        "unidentifiable_directions": [
            "base frame against the targets (6 directions): held at nominal",
            "virtual pin against the last joint's own motion: absorbed by the pin",
        ]
        + (
            ["length scale (no known distance): held at the nominal model's by a gauge constraint"]
            if scale_held
            else []
        ),
        "noise_model": noise_note,
        "flange_sigma_mm": (
            [float(v) * 1e3 for v in sigma_flange] if sigma_flange is not None else None
        ),
        "distances": [
            {
                "a": data.target_labels[a],
                "b": data.target_labels[b],
                "metres": dm,
                "fitted_metres": float(np.linalg.norm(tg[a] - tg[b])),
            }
            for a, b, dm in data.dist
        ],
        "distances_dropped": data.dropped_distances,
        "cost": float(sol.cost),
        "rms_mm": rms * 1e3,
        "max_mm": float(norms_used.max() * 1e3),
        "sigma_mm": math.sqrt(sigma2) * 1e3 if dof > 0 else float("nan"),
        "dof": int(dof),
        **{k: float(v) for k, v in obs.items()},
        **{
            f"predicted_{kind}_{stat}_mm": (float(fn(e) * 1e3) if dof > 0 else float("nan"))
            for kind, e in pred.items()
            for stat, fn in (("rms", lambda a: np.sqrt(np.mean(a**2))), ("max", np.max))
        },
        "predicted_note": (
            "covariance-predicted pin position error over poses spread through the touched "
            "volume, after the same registration as the accuracy figures (shape: similarity, "
            "absolute: rigid; raw: none); random error only (systematic input errors are "
            "invisible to it)"
        ),
        "p_flange_pin": [float(v) for v in pin],
        "solver": {
            "method": "lm" if linear and prob.m >= z0.size else "trf",
            "loss": config.robust_loss,
            "status": int(sol.status),
            "message": str(sol.message),
            "success": bool(sol.success),
            "nfev": int(sol.nfev),
            "njev": int(sol.njev or 0),
            "initial_rms_mm": initial_rms * 1e3,
            "characteristic_length_m": Lc,
        },
        "seconds": seconds,
    }
    not_excited = [model.param_names[int(j)] for j in st.kept[h_loc]]
    summary["conditioning_note"], weak = conditioning_note(
        not_excited, int(r_struct), float(obs["cond"])
    )
    summary["not_excited"] = not_excited
    summary["headline"] = [
        f"identify [{name}]: {N} touch-ups, {K} targets, {len(kept)}/{P} parameters identified; "
        f"residual RMS {rms * 1e3:.4f} mm, covariance-predicted pin error RMS "
        f"{summary['predicted_shape_rms_mm']:.4f} mm (shape), "
        f"{summary['predicted_absolute_rms_mm']:.4f} mm (absolute); cond {obs['cond']:.3g}",
        "scale: " + summary["scale_note"],
    ] + (["conditioning: " + summary["conditioning_note"]] if weak else [])
    if not model.urdf_exact:
        summary["urdf_note"] = (
            f"calibrated URDF of model {name}: its rigid part only (a URDF cannot carry its "
            "configuration-dependent terms); the residuals and figures above are the whole "
            "model's, its values are in parameters.parquet"
        )
        summary["headline"].insert(1, summary["urdf_note"])
    return IdentifyResult(
        model=name,
        parameters=parameters,
        residuals=residuals,
        targets=targets,
        calibrated_urdf=urdf_out,
        summary=summary,
        chain=calibrated,
        p_flange_pin=pin,
        x=x,
        error_model=model,
    )


#: condition number of the scaled, reduced identification Jacobian above which a run warns
COND_WARN = 1e4


def conditioning_note(not_excited: list[str], n_structural: int, cond: float) -> tuple[str, bool]:
    """What the identification's conditioning says, and whether it is a warning.

    The touch-ups' own pivoted QR (``data_tol``) holds the structurally
    identifiable parameters they fail to excite at nominal, so the fitted problem
    stays solvable; what those parameters do to the robot is then simply not
    calibrated. That, or a condition number above :data:`COND_WARN` (the
    sample's 18 touch-ups give 800-1,200), is worth a line.

    Parameters
    ----------
    not_excited : names of the structurally identifiable parameters held for lack of excitation
    n_structural : number of structurally identifiable parameters
    cond : condition number of the scaled identification Jacobian of the fitted parameters
    """
    if not not_excited and cond <= COND_WARN:
        return f"every identifiable parameter excited (cond {cond:.3g})", False
    parts = []
    if not_excited:
        names = ", ".join(not_excited[:6]) + (", ..." if len(not_excited) > 6 else "")
        parts.append(
            f"{len(not_excited)} of {n_structural} identifiable parameters are not excited by "
            f"these touch-ups and stay at nominal ({names})"
        )
    if cond > COND_WARN:
        parts.append(f"cond {cond:.3g} > {COND_WARN:.0e}")
    return (
        "; ".join(parts) + ": add touch-ups in more varied arm orientations (`vtcal plan` "
        "chooses well-conditioned poses)",
        True,
    )


def design_jacobian(
    urdf: str,
    base_link: str,
    flange_link: str,
    q: F64,
    target_ids: np.ndarray,
    p_flange_pin: F64,
    *,
    model: str = DEFAULT_MODEL,
    known_distance: bool = False,
) -> tuple[F64, F64, list[str]]:
    """Identification Jacobian of planned touch-ups on the nominal robot (for pose planning).

    Parameters
    ----------
    urdf, base_link, flange_link : the nominal chain
    q : (N, n) planned converged joint vectors
    target_ids : (N,) which target each touches (any labels)
    p_flange_pin : (3,) the (expected) virtual pin
    model : error model whose structurally identifiable parameters are rated
    known_distance : add a distance row between the first two targets

    Returns
    -------
    J_kin : (m, L) scaled columns of the identifiable kinematic parameters
        (radians times the working radius, so every column is in metres)
    J_nuisance : (m, 3 + 3K) pin and target columns
    names : the L parameter names

    ``pipeline.models.observability.observability(J_kin, J_nuisance)`` rates the set.
    """
    chain = load_chain(urdf, base_link, flange_link)
    labels = list(dict.fromkeys(np.asarray(target_ids).tolist()))
    table = pd.DataFrame(np.asarray(q, dtype=float), columns=chain.joint_names)
    table.insert(0, "target_id", [labels.index(t) for t in np.asarray(target_ids).tolist()])
    table.insert(0, "touchup_id", np.arange(len(table)))
    dist: list[tuple[int | str, int | str, float]] = (
        [(0, 1, 1.0)] if known_distance and len(labels) > 1 else []
    )
    data = _prepare(table, chain, IdentifyConfig(distances=dist))
    m = make_model(model, chain)
    pin = np.asarray(p_flange_pin, dtype=float)
    p, _, _ = m.pin_and_jacobian(m.zero(), data.q, pin, jac=False)
    tg = np.array([p[data.tk == k].mean(axis=0) for k in range(data.K)])
    st = _structure(model, urdf, base_link, flange_link, bool(dist), IdentifyConfig().rank_tol)
    Lc = float(max(np.sqrt(np.mean(np.sum(tg**2, axis=1))), 0.1))
    pscale = m.column_scale(Lc)
    prob = _Problem(m, data, IdentifyConfig())
    _, J = prob.full_eval(m.zero(), pin, tg)
    assert J is not None
    P = m.n_params
    return J[:, st.kept] * pscale[st.kept], J[:, P:], [m.param_names[int(j)] for j in st.kept]


# ----------------------------------------------------------------------------- output


def best_result(results: IdentifyResult | dict[str, IdentifyResult]) -> IdentifyResult:
    """The result whose ``calibrated.urdf`` a run ships: the default model if fitted, else
    the one with the smallest residual RMS."""
    if isinstance(results, IdentifyResult):
        return results
    if DEFAULT_MODEL in results:
        return results[DEFAULT_MODEL]
    return min(results.values(), key=lambda r: r.summary["rms_mm"])


def fit_outputs(results: IdentifyResult | dict[str, IdentifyResult]) -> dict[str, Any]:
    """What the identify stage writes, as data (the runner writes it).

    Returns
    -------
    dict with ``parameters``, ``residuals``, ``targets``: every model's rows in
    one table (``model`` column), as :class:`pipeline.catalog.Parquet` with the
    :func:`best_result`'s ``scale_held`` and ``model`` in the metadata;
    ``model_urdfs``: ``{model: calibrated URDF text}``; ``models``: the JSON
    document ``{"models": {model: summary}, "order": [model, ...], "best_model": name}``
    (NaN as null; ``order``: the order the models were fitted, which headlines follow)
    from which the choose stage (:mod:`pipeline.stages.choose`) makes identify.json.
    """
    from pipeline.catalog import Parquet

    many = results if isinstance(results, dict) else {results.model: results}
    best = best_result(results)
    meta = {"scale_held": json.dumps(best.summary["scale_held"]), "model": best.model}
    tables = {
        key: Parquet(pd.concat([getattr(r, key) for r in many.values()], ignore_index=True), meta)
        for key in ("parameters", "residuals", "targets")
    }
    doc = {
        "models": {n: r.summary for n, r in many.items()},
        "order": list(many),  # the order fitted (JSON files sort their keys)
        "best_model": best.model,
    }
    text = json.dumps(_finite(doc), default=_json_default, allow_nan=False)
    return {
        **tables,
        "model_urdfs": {n: r.calibrated_urdf for n, r in many.items()},
        "models": json.loads(text),
    }


def _finite(o: Any) -> Any:
    """NaN/inf floats -> None, recursively (strict JSON)."""
    if isinstance(o, float | np.floating):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    return o


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
