"""Identification input: the touch-up table as the rows that enter the fit (:class:`FitData`).

Every input row is kept for the residual table with the reason it was or was not
used; the used rows are checked before any fit (too few, implausible joints).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.estimation.correction_frame import table_scatters
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.stages.identify.print_shape import ANISOTROPY_COLUMN, SHAPE_COLUMNS
from pipeline.stages.identify.types import IdentifyConfig

#: rows beyond these are flagged, not fitted: a joint at 1000 rad (or m), a residual correction
#: of a metre or a relative weight of a million is a corrupt value, not a measurement
MAX_JOINT = 1e3
MAX_CORRECTION_M = 1.0
MAX_WEIGHT = 1e6
#: the first reason :func:`_row_reasons` gives a row; "rejected as outlier" comes after it
NOT_CONVERGED = "not converged"


def prepare_data(touchups: pd.DataFrame, chain: Chain, config: IdentifyConfig) -> FitData:
    """The rows of ``touchups`` that enter the fit, with every row's reason kept.

    1. columns checked and made numeric; joints ``q``, residual corrections ``d``
       (``dx_flange`` ...) and weights read;
    2. every row that cannot be used gets its reason (:func:`_row_reasons`);
    3. target labels numbered (:func:`_target_numbers`): integers keep their value;
    4. the known distances matched to the used targets (:func:`_known_distances`);
    5. the print-shape levers of the used rows and every row's image-Jacobian pair
       scatter, when the table has them.

    Fits on subsets of one table's rows (cross-validation) prepare it once instead
    (:func:`prepare_table`, :func:`restrict`).
    """
    return _prepare(touchups, chain, config)[0]


def _prepare(
    touchups: pd.DataFrame, chain: Chain, config: IdentifyConfig
) -> tuple[FitData, F64 | None, set[str]]:
    """:func:`prepare_data`, with what :func:`restrict` needs besides: every row's
    print-shape columns ``(M, 6)`` (None without them) and the text of every target label."""
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
    reason = _row_reasons(df, q_all, d_all, w)
    used = np.array([not r for r in reason], dtype=bool)

    raw_labels = df["target_id"].tolist()
    order, all_int, tid_of, row_tid = _target_numbers(raw_labels)
    row_label = [str(int(lab)) if all_int and lab in tid_of else str(lab) for lab in raw_labels]
    for i in np.flatnonzero(row_tid < 0).tolist():
        reason[i].append("no target label")
        used[i] = False

    used_labels = [lab for lab in order if np.any(used & (row_tid == tid_of[lab]))]
    k_of = {tid_of[lab]: k for k, lab in enumerate(used_labels)}
    tk_all = np.array([k_of.get(int(t), -1) for t in row_tid], dtype=np.int64)
    label_text = [str(int(lab)) if all_int else str(lab) for lab in used_labels]
    all_text = {(str(int(lab)) if all_int else str(lab)) for lab in order}
    dist, dropped = _known_distances(config, label_text, all_text)

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
    shape_all = None
    if all(c in df.columns for c in SHAPE_COLUMNS):
        cols = (
            [*SHAPE_COLUMNS, ANISOTROPY_COLUMN]
            if ANISOTROPY_COLUMN in df.columns
            else SHAPE_COLUMNS
        )
        shape_all = np.stack(
            [pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float) for c in cols], axis=1
        )
    shape_g, shape_l, shape_v = _used_shape(shape_all, ui)
    data = FitData(
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
        shape_v=shape_v,
        pair_scatter_all=table_scatters(df),
    )
    return data, shape_all, all_text


def _used_shape(shape_all: F64 | None, ui: np.ndarray) -> tuple[F64 | None, F64 | None, F64 | None]:
    """The used rows' print-size levers ``g`` and long-axis directions ``l``, ``(N, 3)`` each,
    and their image anisotropy ``(N,)`` (None without its column; NaN rows use (S2)), from
    every row's ``(M, 6)`` or ``(M, 7)`` shape columns; (None, None, None) without them,
    without used rows or when a used row's ``g`` and ``l`` are not numbers."""
    if shape_all is None:
        return None, None, None
    sh = shape_all[ui]
    if len(sh) and np.all(np.isfinite(sh[:, :6])):
        return sh[:, :3], sh[:, 3:6], (sh[:, 6].copy() if sh.shape[1] > 6 else None)
    return None, None, None


@dataclass
class PreparedTable:
    """A touch-up table prepared once for fits on subsets of its rows (:func:`restrict`).

    Attributes
    ----------
    data : :func:`prepare_data` of the table with every row an inlier (its ``inlier``
        column, if any, left out): M rows, the usable ones used
    shape_all : (M, 6) every row's print-shape columns (``SHAPE_COLUMNS`` order), NaN
        where not a number; None when the table lacks them
    all_labels : the text of every target label of the table, used or not (the names a
        known distance may give)
    rejected : (M,) the reason a row gets when a subset leaves it out: "rejected as
        outlier", with the table's ``reason`` in brackets when it gives one
    """

    data: FitData
    shape_all: F64 | None
    all_labels: set[str]
    rejected: list[str]


def prepare_table(touchups: pd.DataFrame, chain: Chain, config: IdentifyConfig) -> PreparedTable:
    """The pandas work of :func:`prepare_data` done once for fits on subsets of the rows.

    Raises what :func:`prepare_data` raises on the table (whatever ``inlier`` column a
    subset's table has, the same: its checks read the columns and every target label).
    """
    table = touchups.drop(columns="inlier") if "inlier" in touchups.columns else touchups
    data, shape_all, all_labels = _prepare(table, chain, config)
    df = table.reset_index(drop=True)
    return PreparedTable(data, shape_all, all_labels, _outlier_reasons(df, np.arange(len(df))))


def restrict(prep: PreparedTable, keep: np.ndarray, config: IdentifyConfig) -> FitData:
    """What :func:`prepare_data` gives on the prepared table with ``inlier = keep``, from ``prep``.

    Parameters
    ----------
    prep : the table, prepared once (:func:`prepare_table`)
    keep : (M,) bool, the table's rows to let in (the ``inlier`` column of the subset)
    config : the fit's settings (its known distances are matched to the targets kept)

    Returns
    -------
    FitData equal field by field to ``prepare_data(table.assign(inlier=keep), chain,
    config)``: the rows ``keep`` leaves out are not used and have "rejected as outlier"
    among their reasons (after "not converged", as :func:`_row_reasons` orders them);
    a target with no used row left leaves the numbering (``tk``, ``K``, ``target_ids``,
    ``target_labels``; the others keep their order), and a known distance naming it is
    dropped with its note. The arrays are copies: the result shares nothing with ``prep``.
    """
    base = prep.data
    M = len(base.rows)
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (M,):
        raise ValueError(f"keep has shape {keep.shape}, expected ({M},)")
    sel = keep[base.used_idx]  # the used rows that stay, (N_base,)
    ui = base.used_idx[sel]
    present = np.zeros(base.K, dtype=bool)
    present[base.tk[sel]] = True
    new_k = np.full(base.K + 1, -1, dtype=np.int64)  # the last entry: tk_all = -1 stays -1
    new_k[: base.K][present] = np.arange(int(present.sum()))
    tk_all = new_k[base.tk_all]
    kept = np.flatnonzero(present).tolist()
    labels = [base.target_labels[k] for k in kept]
    dist, dropped = _known_distances(config, labels, prep.all_labels)
    reasons = base.rows["reason"].tolist()
    for i in np.flatnonzero(~keep).tolist():
        # base reasons are _row_reasons' fixed phrases, none with "; " inside
        parts = reasons[i].split("; ") if reasons[i] else []
        at = 1 if parts[:1] == [NOT_CONVERGED] else 0
        reasons[i] = "; ".join([*parts[:at], prep.rejected[i], *parts[at:]])
    used = np.zeros(M, dtype=bool)
    used[ui] = True
    shape_g, shape_l, shape_v = _used_shape(prep.shape_all, ui)
    ps = base.pair_scatter_all
    return FitData(
        q=base.q[sel],
        d=base.d[sel],
        sw=base.sw[sel],
        tk=tk_all[ui],
        K=len(kept),
        target_ids=[base.target_ids[k] for k in kept],
        target_labels=labels,
        dist=dist,
        dropped_distances=dropped,
        rows=base.rows.assign(used=used, reason=reasons),
        used_idx=ui,
        q_all=base.q_all.copy(),
        d_all=base.d_all.copy(),
        tk_all=tk_all,
        shape_g=shape_g,
        shape_l=shape_l,
        shape_v=shape_v,
        pair_scatter_all=None if ps is None else ps.copy(),
    )


def _row_reasons(df: pd.DataFrame, q_all: F64, d_all: F64, w: F64) -> list[list[str]]:
    """Why each row cannot be used (empty: usable); a missing or corrupt correction is zeroed."""
    M = len(df)
    reason = [[] for _ in range(M)]  # type: list[list[str]]
    if "converged" in df.columns:
        for i in np.flatnonzero(~df["converged"].fillna(False).to_numpy(dtype=bool)).tolist():
            reason[i].append(NOT_CONVERGED)
    if "inlier" in df.columns:
        out = np.flatnonzero(~df["inlier"].fillna(False).to_numpy(dtype=bool))
        for i, why in zip(out.tolist(), _outlier_reasons(df, out), strict=True):
            reason[i].append(why)
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
    return reason


def _outlier_reasons(df: pd.DataFrame, rows: np.ndarray) -> list[str]:
    """The reason of each of ``rows`` (positions) as a row the ``inlier`` column rejects:
    "rejected as outlier", with the table's ``reason`` in brackets when it gives one."""
    rej = df["reason"].astype(str).to_numpy() if "reason" in df.columns else None
    out = []
    for i in rows.tolist():
        extra = f" ({rej[i]})" if rej is not None and rej[i] not in ("", "nan", "None") else ""
        out.append("rejected as outlier" + extra)
    return out


def _target_numbers(
    raw_labels: list[Any],
) -> tuple[list[Any], bool, dict[Any, int], np.ndarray]:
    """(labels in order of appearance, all integers, label -> target id, each row's id or -1).

    A target id is the label's value when every label is an integer, else its rank.
    """
    order: list[Any] = []
    for lab in raw_labels:
        if lab not in order and not (isinstance(lab, float) and math.isnan(lab)):
            order.append(lab)
    all_int = all(
        isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer()) for v in order
    )
    tid_of = {lab: (int(lab) if all_int else i) for i, lab in enumerate(order)}
    row_tid = np.array([tid_of.get(lab, -1) for lab in raw_labels], dtype=np.int64)
    return order, all_int, tid_of, row_tid


def _known_distances(
    config: IdentifyConfig, label_text: list[str], all_text: set[str]
) -> tuple[list[tuple[int, int, float]], list[str]]:
    """(kept, dropped): ``config.distances`` as (target index A, B, metres) among the used targets.

    ``label_text`` names the used targets, ``all_text`` every target of the table; a
    distance to an absent target is dropped, or refused with ``strict_distances``.
    """
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
    return dist, dropped


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


def implausible_rows(
    chain: Chain,
    data: FitData,
    touchups: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    config: IdentifyConfig,
) -> list[str]:
    """The guardrails of :mod:`pipeline.guardrails.plausibility` on the used touch-ups."""
    from pipeline.guardrails import plausibility as pl
    from pipeline.kinematics.urdf import parse_urdf

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


def refuse_early(data: FitData, source_rows: int) -> None:
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
