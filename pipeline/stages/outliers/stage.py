"""Outlier rejection: flag touch-ups that identification must not trust (never delete them).

Two steps, each recording its reason on the row it flags (several reasons are
joined by ``"; "``); every input row comes out, in the same order.

**1. Rules** on what extraction recorded about each touch-up (a rule whose
column is absent from the touch-up table is skipped):

| reason | when |
|---|---|
| ``not converged`` | ``converged`` is false and the final image error ``e_T`` is beyond
  correction: ``|e_u|`` or ``|e_v|`` above ``max_correctable_px``, ``|e_s|`` above
  ``max_correctable_size_px``, or not measured. A touch-up that stopped short of the
  thresholds but within these bounds (a controller whose own detection was biased by
  uneven light, an iteration limit hit a few tenths of a pixel out) is a measurement
  like any other once the residual correction ``d = -J^-1 e_T`` is applied: it is kept,
  with the note ``not converged, corrected by the residual correction``. |
| ``target lost`` | ``lost`` is true, or the blob at the final pose is not the target: its long
  axis is off the designated one (``s - e_s_px``) by more than ``lost_size_frac`` of it |
| ``captured while moving`` | ``moving`` is true |
| ``poor contour fit`` | ``fit_residual_px`` above ``max_fit_residual_px`` |
| ``ambiguous blob`` | ``ambiguous`` is true |
| ``contour cut by the border`` | ``border_contact`` is true |
| ``too few captures`` | ``n_converged_captures`` below ``min_captures`` |

**2. Statistics** on the identification residuals of the rows the rules kept
(needs ``info.urdf``; skipped with a note otherwise). The measurement model is
linearised at the least-squares fit (:func:`pipeline.stages.identify.stage.identify`)::

    e = J dz + eps,    eps ~ N(0, sigma^2 I)

with ``e`` the weighted pin-minus-target residuals (3 per touch-up, plus the
known-distance rows) and ``J`` the identification Jacobian over the identified
kinematic parameters, the pin and the targets. Each alternative is a
*mean shift* of a group of rows, ``e = J dz + C delta + eps`` with ``C``
three columns:

* one touch-up is an outlier: ``C`` selects its three rows;
* a target was knocked after its ``c``-th touch-up in time: ``C`` stacks the
  identity on every row of that target from touch-up ``c + 1`` on (the part
  after the knock sits at ``t + delta``).

The score of a group is the drop in the residual sum of squares its columns
buy (Cook & Weisberg 1982, *Residuals and Influence in Regression*, ch. 2.2,
the mean-shift outlier model)::

    S = (C^T e)^T (C^T (I - H) C)^+ (C^T e),   H = J (J^T J)^+ J^T

so the leverage of every row (the hat matrix ``H``) is accounted for. Rows are
whitened as identification whitens them (``sqrt(w_i) W R_i^T``, ``W`` from the
residuals' covariance in the flange frame, identity when identification stayed
isotropic), and ``e`` is the residual of that whitened linear fit. With
the scale estimated *without* the group, ``s2 = (|e|^2 - S) / (dof - r)``
(``r = rank C^T (I - H) C``), ``F = S / (r s2)`` follows ``F(r, dof - r)``
under "no outlier"; a single touch-up's ``sqrt(S / s2)`` is its externally
studentized residual, reported as ``"residual 5.2 sigma"``. The most
significant group, if its Bonferroni-corrected p-value (times the number of
groups tested) is below ``alpha``, is flagged (an outlier) or split (a knock:
the touch-ups after it get a new target label, ``max label + 1``; the part
before keeps the label, so a known distance involving that target applies to
the part before the knock only), the model is re-fitted and the search
repeats. Groups whose estimated shift ``|delta|`` is below ``min_shift_m``
are not candidates (statistically significant is not the same as worth
rejecting: with a 0.01 mm fit a 0.05 mm slip is "6 sigma"). A shift confined to a target's last touch-up(s) is read as a knock,
which keeps the row (it then only informs its own new target). Finally every
statistically flagged row is re-tested against the final fit as a new
observation (prediction variance ``s2 (I / w + J_i (J^T J)^+ J_i^T)``) and
reinstated when it is consistent with it (guards against swamping).

Which error model the statistics use: ``model="auto"`` takes the richest of
:attr:`OutlierConfig.models` whose fit leaves at least ``min_dof`` degrees of
freedom (a too-simple model leaves systematic residuals that look like outliers).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.estimation.correction_frame import PAIR_COLUMNS
from pipeline.estimation.distributions import f_sf
from pipeline.estimation.whitening import robust_flange_whitening
from pipeline.kinematics.se3 import F64
from pipeline.measurement.pin import ParamLayout, distance_row, whitened_rows
from pipeline.stages.identify.print_shape import ANISOTROPY_COLUMN, SHAPE_COLUMNS

INLIER_COLUMNS = (
    "touchup_id",
    "target_id",
    "dx_flange",
    "dy_flange",
    "dz_flange",
    "weight",
    "converged",
    "stamp_ns",
)


@dataclass
class OutlierConfig:
    """Thresholds of the rejection rules and of the statistical step.

    Attributes
    ----------
    max_fit_residual_px : contour-fit RMS above which a touch-up is rejected, px
    max_correctable_px, max_correctable_size_px : largest remaining centre / long-axis error
        (px) of an unconverged touch-up that the residual correction still turns into a
        measurement. Along the view the correction is exact but for the Jacobian's error
        (``s_inv = z / (f D)`` is linear in the stand-off ``z``): 2.5 px of long axis is ~5 %
        of the stand-off, and a controller that measures size differently from vtcal (a
        binary blob's contour polygon reads ~1.5 px short) stops every touch-up about that
        far off
    min_captures : fewest good captures averaged at the final pose
    lost_size_frac : a final blob whose long axis is off the designated one by more than this
        fraction of it is not the target (an occluder, a reflection): ``target lost``
    statistical : run the residual statistics and the knock search after the rules
    model : error model of the statistics, or ``"auto"`` (see :attr:`models`)
    models : candidates of ``"auto"``, richest first
    min_dof : degrees of freedom ``"auto"`` wants left after the fit
    alpha : family-wise false-alarm probability per search step (Bonferroni)
    split_targets : look for knocked targets (change point in time) and split them
    min_before : fewest inlier touch-ups a target keeps before a knock
    max_iterations : flag/split steps at most
    reinclude : re-test flagged rows against the final fit and reinstate consistent ones
    min_shift_m : smallest shift (of a touch-up or of a knocked target) worth acting on,
        metres: a significant but smaller one is not acted on (its studentized
        residual stays in the table); it moves the calibration by less than a
        touch-up's repeatability
    noise_model : identification's noise model for the statistics (``flange``:
        residuals whitened in the flange frame, as identify does by default;
        ``isotropic``)
    """

    max_fit_residual_px: float = 0.25
    max_correctable_px: float = 2.0
    max_correctable_size_px: float = 2.5
    min_captures: int = 1
    lost_size_frac: float = 0.3
    statistical: bool = True
    model: str = "auto"
    models: list[str] = field(default_factory=lambda: ["full", "mdh", "offsets"])
    min_dof: int = 10
    alpha: float = 0.01
    split_targets: bool = True
    min_before: int = 2
    max_iterations: int = 20
    reinclude: bool = True
    min_shift_m: float = 1e-4
    noise_model: str = "flange"


def _rule_masks(table: pd.DataFrame, config: OutlierConfig) -> dict[str, np.ndarray]:
    n = len(table)

    def col(name: str, default: Any) -> np.ndarray:
        if name in table.columns:
            return table[name].fillna(default).to_numpy()
        return np.full(n, default)

    s_final = col("s", np.nan).astype(float)
    e_s = col("e_s_px", np.nan).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        not_target = np.abs(e_s) > config.lost_size_frac * np.abs(s_final - e_s)
    return {
        "not converged": ~col("converged", True).astype(bool) & ~correctable(table, config),
        "target lost": col("lost", False).astype(bool) | not_target,  # NaN compares False
        "captured while moving": col("moving", False).astype(bool),
        "poor contour fit": col("fit_residual_px", 0.0).astype(float) > config.max_fit_residual_px,
        "ambiguous blob": col("ambiguous", False).astype(bool),
        "contour cut by the border": col("border_contact", False).astype(bool),
        "too few captures": col("n_converged_captures", config.min_captures).astype(float)
        < config.min_captures,
    }


def correctable(table: pd.DataFrame, config: OutlierConfig) -> np.ndarray:
    """Rows whose final image error the residual correction can remove (see the rules table).

    Needs ``e_u``, ``e_v``, ``e_s_px`` (vtcal's touch-up artefact); a table without
    them (a spec touch-up table) has nothing to correct with: all False.
    """
    n = len(table)
    if not {"e_u", "e_v", "e_s_px"} <= set(table.columns):
        return np.zeros(n, dtype=bool)
    e = table[["e_u", "e_v", "e_s_px"]].to_numpy(dtype=float)
    lost = (
        table["lost"].fillna(False).to_numpy(dtype=bool) if "lost" in table else np.zeros(n, bool)
    )
    with np.errstate(invalid="ignore"):
        ok = (
            np.isfinite(e).all(axis=1)
            & (np.abs(e[:, 0]) <= config.max_correctable_px)
            & (np.abs(e[:, 1]) <= config.max_correctable_px)
            & (np.abs(e[:, 2]) <= config.max_correctable_size_px)
        )
    result: np.ndarray = ok & ~lost
    return result


def flag_outliers(table: pd.DataFrame, info: Any, config: OutlierConfig) -> pd.DataFrame:
    """Flag rejected touch-ups with their reasons; split knocked targets.

    Parameters
    ----------
    table : touchups artefact (``schemas/touchups.json``), or any touch-up table
        (``spec/touchups.md``)
    info : RecordingInfo: ``joint_names``; for the statistics also ``urdf``,
        ``base_link``, ``flange_link`` and ``metadata["known_distances"]``
    config : OutlierConfig

    Returns
    -------
    DataFrame per ``schemas/inliers.json``: the spec's touch-up columns, the joint
    columns, ``source_target_id`` (label as extracted), ``target_id`` (after
    knock splits), ``inlier``, ``reason``, ``studentized`` (sigma, NaN if not
    tested), ``leverage`` and ``note``; one row per input row, same order.
    """
    joints = list(info.joint_names)
    base = table.reset_index(drop=True)
    cols = [c for c in INLIER_COLUMNS if c in base.columns]
    out = base[cols + joints].copy()
    for c, default in (
        ("dx_flange", 0.0),
        ("dy_flange", 0.0),
        ("dz_flange", 0.0),
        ("weight", 1.0),
        ("converged", True),
    ):
        if c not in out.columns:
            out[c] = default
    if "stamp_ns" not in out.columns:
        out["stamp_ns"] = np.arange(len(out), dtype=np.int64)
    out = out[list(INLIER_COLUMNS) + joints]
    out.insert(2, "source_target_id", base["target_id"].to_numpy())
    masks = _rule_masks(base, config)
    reasons = ["; ".join(r for r, m in masks.items() if m[i]) for i in range(len(base))]
    out["inlier"] = [r == "" for r in reasons]
    out["reason"] = reasons
    out["studentized"] = out["leverage"] = np.nan
    conv = base["converged"].fillna(True).to_numpy(dtype=bool) if "converged" in base else None
    fixed = (~conv & correctable(base, config)) if conv is not None else np.zeros(len(base), bool)
    out["note"] = [
        "not converged, corrected by the residual correction (e_T {:+.2f}, {:+.2f}, {:+.2f} px)".format(
            *base.loc[i, ["e_u", "e_v", "e_s_px"]].to_numpy(dtype=float)
        )
        if fixed[i]
        else ""
        for i in range(len(base))
    ]
    # identification uses converged rows: a corrected one counts as converged from here on
    out.loc[fixed, "converged"] = True
    for c in (*SHAPE_COLUMNS, ANISOTROPY_COLUMN, *PAIR_COLUMNS):
        out[c] = (
            pd.to_numeric(base[c], errors="coerce").to_numpy(dtype=float)
            if c in base
            else np.full(len(base), np.nan)
        )
    labels = pd.to_numeric(out["target_id"], errors="coerce")
    if config.statistical and getattr(info, "urdf", None):
        if labels.notna().all() and (labels == labels.round()).all():
            out = _statistical(out, info, config)
        else:
            out["note"] = "statistical check skipped (target labels are not integers)"
    return out.reset_index(drop=True)


# ----------------------------------------------------------------------------- statistics


@dataclass
class _Fit:
    """A least-squares fit linearised for the mean-shift tests.

    ``rows`` are positions (in the flagged table) of the touch-ups in the fit,
    ``e`` (m,) the weighted, whitened residual (projected onto the orthogonal
    complement of the Jacobian's columns: the linearised least-squares residual), ``U`` (m, rank) an orthonormal basis of
    the Jacobian's column space, ``dof = m - rank``, ``sigma2 = |e|^2 / dof``;
    ``Vs`` (cols, rank) = ``V S^-1`` so ``(J^T J)^+ = Vs Vs^T``.
    """

    model: str
    rows: np.ndarray
    B: F64  # (N, 3, 3) whitening block of each touch-up: sqrt(w_i) W R_i^T (or sqrt(w_i) I)
    W: F64  # (3, 3) flange-frame whitening (identity: isotropic)
    e: F64
    U: F64
    Vs: F64
    dof: int
    sigma2: float
    x: F64
    kept: np.ndarray
    pin: F64
    targets: dict[int, F64]
    tcol: dict[int, int]
    M: F64  # (3, 3) the fit's correction map (IdentifyResult.correction_map)
    singles: dict[int, tuple[float, float, int, F64]] = field(default_factory=dict)  # _test's


def _fit(out: pd.DataFrame, info: Any, model: str, config: OutlierConfig) -> _Fit:
    """Identify on the current inliers and build the linearised problem."""
    from pipeline.io.known_distances import metadata_distances
    from pipeline.kinematics.chain import load_chain
    from pipeline.models import make_model
    from pipeline.stages.identify.stage import IdentifyConfig, IdentifyResult, identify

    dist = metadata_distances(getattr(info, "metadata", None))
    labels = {str(v) for v in out["target_id"].tolist()}  # a label may be a name
    dist = [d for d in dist if str(d[0]) in labels and str(d[1]) in labels]
    # no guardrails: they are the identify stage's to judge (and --accept-implausible's);
    # here an accepted implausible input made every statistical test skip
    icfg = IdentifyConfig(
        model=model,
        distances=dist,
        n_workspace=4,
        noise_model=config.noise_model,
        check_plausibility=False,
    )
    res = identify(out, info.urdf, info.base_link, info.flange_link, icfg)
    assert isinstance(res, IdentifyResult)
    chain = load_chain(info.urdf, info.base_link, info.flange_link)
    em = make_model(model, chain)
    par = res.parameters
    kin = par[par["kind"] == "kinematic"].reset_index(drop=True)
    kept = np.flatnonzero(kin["identifiable"].to_numpy(dtype=bool))
    ids = res.targets["target_id"].to_numpy(dtype=np.int64)
    xyz = res.targets[["x", "y", "z"]].to_numpy(dtype=float)
    tg = {int(t): xyz[i] for i, t in enumerate(ids)}  # fitted target positions
    tcol = {t: i for i, t in enumerate(sorted(tg))}
    rows = np.flatnonzero(res.residuals["used"].to_numpy(dtype=bool))
    q = out.iloc[rows][list(chain.joint_names)].to_numpy(dtype=float)
    d = out.iloc[rows][["dx_flange", "dy_flange", "dz_flange"]].to_numpy(dtype=float)
    d = d @ res.correction_map.T  # in the fit's frame (IdentifyConfig.correction_frame)
    sw = np.sqrt(out.iloc[rows]["weight"].to_numpy(dtype=float))
    tid = out.iloc[rows]["target_id"].to_numpy(dtype=int)
    p, R, Jx = em.pin_and_jacobian(res.x, q, res.p_flange_pin + d, jac=True)
    assert Jx is not None
    N, nk = len(rows), len(kept)
    lay = ParamLayout(nk, len(tg))  # [identified kinematic | pin | targets in sorted order]
    t_at = np.array([tg[int(t)] for t in tid])
    W = robust_flange_whitening(R, p - t_at, sw**2, lay.n, bool(res.summary.get("flange_sigma_mm")))
    B = np.einsum("ab,ncb->nac", W, R) * sw[:, None, None]  # sqrt(w) W R^T
    e_rows = np.einsum("nab,nb->na", B, p - t_at).ravel()
    tcols = np.array([tcol[int(t)] for t in tid], dtype=np.int64)
    J = whitened_rows(lay, B, Jx[:, :, kept], R, tcols, einsum=True).reshape(3 * N, lay.n)
    # known-distance rows (their residuals are ~0 at the fit, weight as in identify)
    wd = float(icfg.distance_weight)
    extra_J, extra_e = [], []
    for a, b, metres in dist:
        ta, tb = tg.get(int(a)), tg.get(int(b))
        if ta is None or tb is None:
            continue
        row, res_d = distance_row(lay, ta, tb, tcol[int(a)], tcol[int(b)], metres, wd)
        extra_J.append(row)
        extra_e.append(res_d)
    if extra_J:
        J = np.vstack([J, np.array(extra_J)])
        e = np.concatenate([e_rows, np.array(extra_e)])
    else:
        e = e_rows
    # column scaling does not change the column space; it keeps the SVD well conditioned
    cn = np.linalg.norm(J, axis=0)
    cn[cn == 0] = 1.0
    Uf, s, Vt = np.linalg.svd(J / cn, full_matrices=False)
    rank = int(np.sum(s > s[0] * 1e-10)) if s.size else 0
    U = Uf[:, :rank]
    Vs = (Vt[:rank].T / s[:rank]) / cn[:, None]
    e = e - U @ (U.T @ e)  # one Gauss-Newton step: the residual of the whitened linear fit
    dof = J.shape[0] - rank
    sigma2 = float(e @ e / dof) if dof > 0 else float("nan")
    x, pin, M = res.x, res.p_flange_pin, res.correction_map
    return _Fit(model, rows, B, W, e, U, Vs, dof, sigma2, x, kept, pin, tg, tcol, M)


def _mean_shift(f: _Fit, pos: np.ndarray, w: np.ndarray) -> tuple[float, int, F64]:
    """``(S, r, delta)`` of the mean-shift model for the touch-ups at fit positions ``pos``.

    ``S`` is the drop in the residual sum of squares that three shift columns
    ``C`` on those rows buy, ``r`` the rank of ``C^T (I - H) C`` and ``delta``
    the least-squares shift, metres (module docstring).
    """
    del w  # the weights are in the whitening blocks
    m = len(f.e)
    C = np.zeros((m, 3))
    for i in pos:
        C[3 * i : 3 * i + 3] = f.B[i]
    UC = f.U.T @ C
    M = C.T @ C - UC.T @ UC
    ce = C.T @ f.e
    ev = np.linalg.eigvalsh(M)
    r = int(np.sum(ev > max(ev.max(), 1e-300) * 1e-8)) if ev.size else 0
    if r == 0:
        return 0.0, 0, np.zeros(3)
    Mi = np.linalg.pinv(M, rcond=1e-8)
    return float(ce @ Mi @ ce), r, Mi @ ce


def _group_test(f: _Fit, pos: np.ndarray, w: np.ndarray) -> tuple[float, float, int, F64]:
    """Mean-shift test of the touch-ups at fit positions ``pos`` (see module docstring).

    Returns ``(p-value, studentized sigma, rank, delta)``; p = 1 when untestable.
    """
    S, r, delta = _mean_shift(f, pos, w)
    if r == 0 or f.dof - r < 1:
        return 1.0, 0.0, 0, np.zeros(3)
    rss = float(f.e @ f.e)
    s2 = max(rss - S, 1e-300) / (f.dof - r)
    F = S / (r * s2)
    p = float(f_sf(F, r, f.dof - r))
    return p, float(np.sqrt(S / s2)), r, delta


def _test(f: _Fit, pos: np.ndarray, w: np.ndarray) -> tuple[float, float, int, F64]:
    """:func:`_group_test` at fit positions ``pos`` (``w`` every fit row's weight); a single
    touch-up's kept on the fit (the search and the final figures test it again)."""
    if len(pos) != 1:
        return _group_test(f, pos, w[pos])
    if int(pos[0]) not in f.singles:
        f.singles[int(pos[0])] = _group_test(f, pos, w[pos])
    return f.singles[int(pos[0])]


def _prediction_test(f: _Fit, out: pd.DataFrame, i: int, info: Any) -> tuple[float, float]:
    """Test row ``i`` (not in the fit) as a new observation of the fit.

    ``e = B_i (p(q_i) - t_k)`` whitened as the fit's rows (``B_i = sqrt(w_i) W R_i^T``),
    ``Var e = s2 (I + J_i (J^T J)^+ J_i^T)`` with ``J_i`` its whitened Jacobian rows;
    returns ``(p-value of F(3, dof), sigma)``.
    """
    from pipeline.kinematics.chain import load_chain
    from pipeline.models import make_model

    tid = int(out["target_id"].to_numpy(dtype=np.int64)[i])
    if tid not in f.targets or not f.dof > 0:
        return 1.0, 0.0
    chain = load_chain(info.urdf, info.base_link, info.flange_link)
    em = make_model(f.model, chain)
    q = out.iloc[[i]][list(chain.joint_names)].to_numpy(dtype=float)
    d = out.iloc[[i]][["dx_flange", "dy_flange", "dz_flange"]].to_numpy(dtype=float)
    w = float(out["weight"].iloc[i])
    if not (np.all(np.isfinite(q)) and w > 0):
        return 1.0, 0.0
    p, R, Jx = em.pin_and_jacobian(f.x, q, f.pin + np.nan_to_num(d) @ f.M.T, jac=True)
    assert Jx is not None
    Bi = np.sqrt(w) * f.W @ R[0].T
    lay = ParamLayout(len(f.kept), len(f.targets))
    Ji = whitened_rows(lay, Bi[None], Jx[:, :, f.kept], R, [f.tcol[tid]])[0]
    G = Ji @ f.Vs
    V = np.eye(3) + G @ G.T
    e = Bi @ (p[0] - f.targets[tid])
    S = float(e @ np.linalg.solve(V, e)) / f.sigma2
    return float(f_sf(S / 3.0, 3, f.dof)), float(np.sqrt(S))


def _leverage(f: _Fit) -> F64:
    """Mean diagonal of the 3x3 hat-matrix block of each touch-up in the fit, (N,)."""
    N = len(f.rows)
    h = np.sum(f.U[: 3 * N] ** 2, axis=1).reshape(N, 3)
    return np.asarray(h.mean(axis=1))


def _choose_fit(out: pd.DataFrame, info: Any, config: OutlierConfig) -> _Fit | str:
    """The fit of the configured (or richest adequate) model, or why there is none."""
    from pipeline.errors import BadInput, CalibrationFailed

    names = list(config.models) if config.model == "auto" else [config.model]
    why = []
    for name in names:
        try:
            f = _fit(out, info, name, config)
        except (BadInput, CalibrationFailed) as exc:
            why.append(f"{name}: {exc}")
            continue
        if config.model != "auto" or f.dof >= config.min_dof or name == names[-1]:
            if f.dof < 4:
                why.append(f"{name}: {f.dof} degrees of freedom left")
                continue
            return f
        why.append(f"{name}: only {f.dof} degrees of freedom left")
    return "statistical check skipped (" + " | ".join(why) + ")"


def _statistical(out: pd.DataFrame, info: Any, config: OutlierConfig) -> pd.DataFrame:
    """Step 2 of the module docstring on the rows the rules kept."""
    out = out.copy()
    out["target_id"] = out["target_id"].astype(np.int64)
    stamps = out["stamp_ns"].to_numpy(dtype=np.int64)
    notes: list[list[str]] = [[n] if n else [] for n in out["note"].astype(str)]
    flagged: list[int] = []
    next_label = int(max(out["target_id"].max(), out["source_target_id"].max())) + 1
    model_used = config.model
    f: _Fit | None = None
    for it in range(config.max_iterations + 1):
        got = _choose_fit(out, info, config if model_used == "auto" else _fixed(config, model_used))
        if isinstance(got, str):
            if it > 0:  # an earlier step left too little to test further
                got = got.replace("statistical check skipped", "statistical search stopped", 1)
            for i in np.flatnonzero(out["inlier"].to_numpy(dtype=bool)):
                notes[i].append(got)
            f = None
            break
        f = got
        model_used = f.model
        cands = _candidates(f, out, stamps, config)
        if not cands:
            break
        n_tests = len(cands)
        # most significant first; a tie (same rows) goes to the knock (kind 0)
        cands.sort(key=lambda c: (round(np.log(max(c[0], 1e-300)), 9), c[1]))
        p, _, kind, what, sig, delta = cands[0]
        if min(1.0, p * n_tests) >= config.alpha:
            break
        if it == config.max_iterations:
            for i in f.rows:
                notes[int(i)].append(f"statistical search stopped after {it} steps")
            break
        if kind == "single":
            r_out = int(what)
            out.loc[r_out, "inlier"] = False
            out.loc[r_out, "reason"] = f"residual {sig:.1f} sigma"
            out.loc[r_out, "studentized"] = sig
            notes[r_out].append(
                f"mean-shift test, model {f.model}: p = {p:.2g} over {n_tests} tests "
                f"(shift {np.linalg.norm(delta) * 1e3:.3f} mm)"
            )
            flagged.append(r_out)
        else:
            t, last_before, after = what
            t_first = stamps[after[0]]
            src = out["target_id"].to_numpy(dtype=np.int64) == t
            move = src & (stamps >= t_first)
            new = next_label
            next_label += 1
            out.loc[move, "target_id"] = new
            for r_mv in np.flatnonzero(move).tolist():
                notes[r_mv].append(
                    f"target {t} knocked between touch-ups {int(out['touchup_id'].iloc[last_before])}"
                    f" and {int(out['touchup_id'].iloc[after[0]])}: the part after is target {new}"
                    f" (shift {np.linalg.norm(delta) * 1e3:.3f} mm, {sig:.1f} sigma, model "
                    f"{f.model})"
                )
    # re-test every statistically flagged row against the final fit
    if f is not None and config.reinclude and flagged:
        n_tests = len(flagged)
        back = []
        for r_fl in flagged:
            p, sig = _prediction_test(f, out, r_fl, info)
            if min(1.0, p * n_tests) >= config.alpha:
                back.append(r_fl)
        for r_bk in back:
            out.loc[r_bk, "inlier"] = True
            out.loc[r_bk, "reason"] = ""
            notes[r_bk].append("reinstated: consistent with the final fit")
        if back:
            got = _choose_fit(out, info, _fixed(config, f.model))
            f = got if isinstance(got, _Fit) else f
    if f is not None:
        lev, w = _leverage(f), out["weight"].to_numpy(dtype=float)[f.rows]
        at = out.index.get_indexer(pd.Index(np.asarray(f.rows, dtype=np.int64)))  # 1 write/column
        levc, stud = np.full(len(out), np.nan), out["studentized"].to_numpy(float).copy()
        for k in range(len(f.rows)):
            _, sig, rk, _ = _test(f, np.array([k]), w)
            levc[at[k]], stud[at[k]] = lev[k], sig if rk else np.nan
        out["leverage"], out["studentized"] = levc, stud
    out["note"] = ["; ".join(n) for n in notes]
    return out


def _candidates(
    f: _Fit, out: pd.DataFrame, stamps: np.ndarray, config: OutlierConfig
) -> list[tuple[float, int, str, Any, float, F64]]:
    """Mean-shift groups worth acting on: (p, kind order, kind, rows, sigma, shift)."""
    w = out["weight"].to_numpy(dtype=float)[f.rows]
    cands: list[tuple[float, int, str, Any, float, F64]] = []
    pos_of = {int(r): k for k, r in enumerate(f.rows)}
    # single touch-ups
    for k, r in enumerate(f.rows):
        p, sig, rk, delta = _test(f, np.array([k]), w)
        if rk and np.linalg.norm(delta) >= config.min_shift_m:
            cands.append((p, 1, "single", int(r), sig, delta))
    # knocks: change point in time per target
    if config.split_targets:
        tids = out["target_id"].to_numpy(dtype=np.int64)
        for t in sorted(set(tids[f.rows].tolist())):
            rows_t = [int(r) for r in f.rows if tids[r] == t]
            rows_t.sort(key=lambda r: (stamps[r], r))
            for c in range(config.min_before, len(rows_t)):
                after = rows_t[c:]
                pos = np.array([pos_of[r] for r in after])
                p, sig, rk, delta = _test(f, pos, w)  # a last touch-up alone: its single test
                if rk and np.linalg.norm(delta) >= config.min_shift_m:
                    cands.append((p, 0, "split", (t, rows_t[c - 1], after), sig, delta))
    return cands


def _fixed(config: OutlierConfig, model: str) -> OutlierConfig:
    return dataclasses.replace(config, model=model)
