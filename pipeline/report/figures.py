"""The report's figures from a run's artefacts: geometry, accuracy, residual statistics.

Everything here reads a :class:`pipeline.report.data.RunData`; nothing writes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.kinematics.chain import Chain, fk_frames
from pipeline.report.data import PIN_LINK, RunData

NOMINAL = "nominal"


def skeleton_points(chain: Chain, q: np.ndarray) -> np.ndarray:
    """Joint-frame origins then the tip origin: ``(N, n + 2, 3)`` m, base origin first.

    ``[0, o_1, ..., o_n, o_tip]`` with ``o_k = T_base_joint_k[:3, 3]`` from
    :func:`pipeline.kinematics.chain.fk_frames`: the line strip a viewer draws as
    the robot's kinematic skeleton.
    """
    T_tip, T_joints = fk_frames(chain, np.atleast_2d(q))
    N = T_tip.shape[0]
    pts = np.concatenate(
        [np.zeros((N, 1, 3)), T_joints[:, :, :3, 3], T_tip[:, None, :3, 3]], axis=1
    )
    return pts


def chosen_model(data: RunData) -> str | None:
    """The error model the run reports (identify.json ``model``), if named."""
    idf = data.identify or {}
    m = idf.get("best_model") or idf.get("model")
    return str(m) if m else None


def for_model(data: RunData, df: pd.DataFrame | None) -> pd.DataFrame | None:
    """Rows of a per-model artefact for the reported model (all rows if it has no model column)."""
    if df is None or "model" not in df.columns or not len(df):
        return df
    m = chosen_model(data)
    models = [str(x) for x in pd.unique(df["model"])]
    pick = m if m in models else models[0]
    return df[df["model"].astype(str) == pick]


def target_positions(data: RunData) -> dict[int, np.ndarray]:
    """``{target_id: p_base_target (3,)}`` m from targets.parquet (reported model)."""
    df = for_model(data, data.targets)
    if df is None or not len(df):
        return {}
    cols = _first_cols(df, [("x", "y", "z"), ("x_m", "y_m", "z_m"), ("px", "py", "pz")])
    if cols is None or "target_id" not in df:
        return {}
    return {
        int(r["target_id"]): np.array([r[c] for c in cols], dtype=float) for _, r in df.iterrows()
    }


def _first_cols(df: pd.DataFrame, options: list[tuple[str, ...]]) -> tuple[str, ...] | None:
    for opt in options:
        if all(c in df.columns for c in opt):
            return opt
    return None


def pin_positions(data: RunData, df: pd.DataFrame) -> np.ndarray | None:
    """Calibrated virtual-pin positions ``(N, 3)`` m in the base frame at each row's ``q``.

    ``p_base_pin = T_base_pin(q)[:3, 3]`` with the chain of calibrated.urdf to
    ``virtual_pin``, the residual correction ``(dx, dy, dz)_flange`` added in the
    flange frame when present (``touchups.md``).
    """
    ch = data.calibrated_chain()
    q = data.joint_matrix(df)
    if ch is None or q is None or ch.tip_link != PIN_LINK:
        return None
    T = fk_frames(ch, q)[0]
    p = T[:, :3, 3].copy()
    d = _first_cols(df, [("dx_flange", "dy_flange", "dz_flange")])
    if d is not None:
        dfl = df[list(d)].to_numpy(dtype=float)
        dfl = np.nan_to_num(dfl)
        p += np.einsum("nij,nj->ni", T[:, :3, :3], dfl)
    return p


@dataclass
class Figure:
    """One accuracy figure of the verdict: ``rms_mm`` and ``max_mm`` over ``n`` points."""

    label: str
    rms_mm: float | None
    max_mm: float | None
    n: int | None = None
    note: str = ""


def _stats_mm(norms_m: np.ndarray) -> tuple[float, float]:
    x = np.asarray(norms_m, dtype=float)
    x = x[np.isfinite(x)]
    if not len(x):
        return math.nan, math.nan
    return float(np.sqrt(np.mean(x * x)) * 1e3), float(np.max(x) * 1e3)


def residual_norms(df: pd.DataFrame) -> np.ndarray | None:
    """Residual lengths (m) of a residual table: a norm column or the norm of x/y/z columns."""
    for c in ("norm", "norm_m", "distance", "error_m", "residual_m", "r"):
        if c in df.columns:
            return df[c].to_numpy(dtype=float)
    cols = _first_cols(
        df,
        [("ex", "ey", "ez"), ("rx", "ry", "rz"), ("dx", "dy", "dz"), ("x", "y", "z"),
         ("ex_m", "ey_m", "ez_m"), ("rx_m", "ry_m", "rz_m")],
    )  # fmt: skip
    if cols is None:
        return None
    return np.linalg.norm(df[list(cols)].to_numpy(dtype=float), axis=1)


def residual_vectors(df: pd.DataFrame) -> np.ndarray | None:
    """Residual vectors ``(N, 3)`` m of a residual table, or None."""
    cols = _first_cols(
        df,
        [("ex", "ey", "ez"), ("rx", "ry", "rz"), ("dx", "dy", "dz"),
         ("ex_m", "ey_m", "ez_m"), ("rx_m", "ry_m", "rz_m")],
    )  # fmt: skip
    if cols is None:
        return None
    return df[list(cols)].to_numpy(dtype=float)


def residual_groups(data: RunData) -> dict[str, pd.DataFrame]:
    """Residual rows of the used touch-ups, per model: ``nominal`` first, then the reported model.

    ``nominal`` is :func:`nominal_fit` (the nominal robot with its best pin and
    targets); the others come from residuals.parquet, one group per error model
    (rows with ``used``/``inlier`` false and rows without a residual left out).
    Computed once per load (``data.derived``): the verdict, the residual plots and the
    accuracy table share them.
    """
    if "residual_groups" not in data.derived:
        data.derived["residual_groups"] = _residual_groups(data)
    got: dict[str, pd.DataFrame] = data.derived["residual_groups"]
    return got


def _residual_groups(data: RunData) -> dict[str, pd.DataFrame]:
    out: dict[str, pd.DataFrame] = {}
    nom = nominal_fit(data)
    if nom is not None and len(nom):
        out[NOMINAL] = nom
    df = data.residuals
    if df is None or not len(df):
        return out
    for flag in ("used", "inlier"):
        if flag in df.columns:
            df = df[df[flag].astype(bool)]
    if "model" not in df.columns:
        out["calibrated"] = df
        return out
    models = [str(m) for m in pd.unique(df["model"])]
    chosen = chosen_model(data)
    if chosen in models:
        models.remove(chosen)
        models.insert(0, chosen)
    for m in models:
        g = df[df["model"].astype(str) == m]
        n = residual_norms(g)
        if n is not None and np.isfinite(n).any():
            out[m if m != NOMINAL else f"{m} (fitted)"] = g[np.isfinite(n)]
    return out


def _num(d: dict[str, Any], *keys: str) -> float | None:
    for k in keys:
        v = d.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            return float(v)
    return None


def _mm(d: dict[str, Any], what: str) -> float | None:
    """``d[what + "_mm"]``, else ``d[what + "_m"]`` or ``d[what]`` (metres) in mm."""
    v = _num(d, f"{what}_mm")
    if v is not None:
        return v
    v = _num(d, f"{what}_m", what)
    return v * 1e3 if v is not None else None


def accuracy_figures(data: RunData) -> list[Figure]:
    """The verdict's accuracy rows (mm), before and after, from whatever the run holds.

    Sources, in order: residuals.parquet (RMS and max of the residual lengths
    per model label), identify.json (``predicted`` figures and any
    ``rms_*``/``max_*`` entries), crossval.parquet (held-out residuals per model).
    """
    figs: list[Figure] = []
    for label, g in residual_groups(data).items():
        n = residual_norms(g)
        if n is None:
            continue
        rms, mx = _stats_mm(n)
        if label == NOMINAL:
            text = "fit residual, nominal robot (best pin and targets)"
        else:
            text = f"fit residual, model {label}"
        figs.append(Figure(text, rms, mx, len(n)))
    idf = data.identify or {}
    for stage in ("before", "after", "nominal", "calibrated"):
        sub = idf.get(stage)
        if isinstance(sub, dict):
            r_mm, m_mm = _mm(sub, "rms"), _mm(sub, "max")
            if r_mm is not None or m_mm is not None:
                figs.append(Figure(f"identify: {stage}", r_mm, m_mm))
    scale_held = bool(idf.get("scale_held", True))
    for kind, text in (
        ("shape", "predicted shape accuracy (similarity registration)"),
        ("absolute", "predicted absolute accuracy (rigid registration)"),
        ("", "predicted pin error (from the parameter covariance)"),
    ):
        key = f"predicted_{kind}_" if kind else "predicted_"
        p_rms, p_max = _num(idf, key + "rms_mm"), _num(idf, key + "max_mm")
        if p_rms is None and p_max is None:
            continue
        note = ""
        if kind == "absolute" and scale_held:
            note = "not reachable: no known distance, the scale was held at nominal"
        figs.append(Figure(text, p_rms, p_max, note=note))
    pred = idf.get("predicted")
    if isinstance(pred, dict):
        figs.append(
            Figure("predicted (from parameter covariance)", _mm(pred, "rms"), _mm(pred, "max"))
        )
    for row in crossval_summary(data):
        for scheme, text in (("kfold", "k-fold"), ("loto", "leave one target out")):
            if row[f"{scheme}_n"]:
                figs.append(
                    Figure(
                        f"cross-validated ({text}), model {row['model']}",
                        row[f"{scheme}_rms_mm"],
                        row[f"{scheme}_max_mm"],
                        row[f"{scheme}_n"],
                    )
                )
    return figs


def crossval_summary(data: RunData) -> list[dict[str, Any]]:
    """Held-out RMS/max (mm) per error model and scheme from crossval.parquet.

    Returns one dict per model: ``model``, and for each scheme ``s`` in
    (``kfold``, ``loto``) ``s_rms_mm``, ``s_max_mm``, ``s_n`` (scored touch-ups)
    and ``s_unscored`` (rows with a status). Without a ``scheme`` column every
    row counts as ``kfold``; residual lengths come from ``error_mm`` or from the
    residual vector columns (m). Computed once per load (``data.derived``): the accuracy
    table and the cross-validation section share them.
    """
    if "crossval_summary" not in data.derived:
        data.derived["crossval_summary"] = _crossval_summary(data)
    got: list[dict[str, Any]] = data.derived["crossval_summary"]
    return got


def _crossval_summary(data: RunData) -> list[dict[str, Any]]:
    df = data.crossval
    if df is None or not len(df):
        return []
    key = next((c for c in ("model", "error_model", "name") if c in df.columns), None)
    groups = list(df.groupby(key, sort=False)) if key else [("model", df)]
    out = []
    for name, g in groups:
        row: dict[str, Any] = {"model": str(name)}
        for scheme in ("kfold", "loto"):
            if "scheme" in g.columns:
                gs = g[g["scheme"] == scheme]
            else:
                gs = g if scheme == "kfold" else g.iloc[:0]
            if "error_mm" in gs.columns:
                e = gs["error_mm"].to_numpy(dtype=float) / 1e3
            else:
                n = residual_norms(gs)
                e = n if n is not None else np.full(len(gs), np.nan)
            ok = np.isfinite(e)
            if "status" in gs.columns:
                ok &= (gs["status"].fillna("").astype(str) == "").to_numpy()
            rms, mx = _stats_mm(e[ok]) if ok.any() else (None, None)
            row[f"{scheme}_rms_mm"] = rms
            row[f"{scheme}_max_mm"] = mx
            row[f"{scheme}_n"] = int(ok.sum())
            row[f"{scheme}_unscored"] = int(len(gs) - ok.sum())
        out.append(row)
    return out


def nominal_fit(data: RunData) -> pd.DataFrame | None:
    """Residuals of the nominal robot with its best virtual pin and target positions.

    The "before" of the verdict: with the nominal kinematics fixed, the pin
    point ``p`` (flange frame) and the target centres ``c_k`` (base frame) that
    best explain the used touch-ups solve a linear least-squares problem,

        R_i (p + d_i) + t_i = c_{k(i)}   =>   [R_i, -E_k] [p; c] = -(t_i + R_i d_i),

    with ``(R_i, t_i) = T_base_flange(q_i)`` and ``d_i`` the residual correction
    ``(dx, dy, dz)_flange``. Its residuals are what the nominal model leaves
    before any kinematic parameter is touched. Returns a table ``touchup_id,
    target_id, rx, ry, rz, norm`` (m) or None when inputs are missing.

    No artefact holds these residuals (identify.json keeps only each model's
    initial RMS), so they are computed here, once per loaded run folder
    (``data.derived``): the verdict, the residual plots and the accuracy table share them.
    """
    if "nominal_fit" not in data.derived:
        data.derived["nominal_fit"] = _nominal_fit(data)
    got: pd.DataFrame | None = data.derived["nominal_fit"]
    return got


def _nominal_fit(data: RunData) -> pd.DataFrame | None:
    """:func:`nominal_fit`, computed."""
    chain = data.nominal_chain()
    tu = data.touchup_table()
    if chain is None or tu is None or "target_id" not in tu:
        return None
    if "inlier" in tu:
        tu = tu[tu["inlier"].astype(bool)]
    q = data.joint_matrix(tu)
    if q is None or len(tu) < 2:
        return None
    from pipeline.measurement.pin import fit_pin_and_targets

    d = np.zeros((len(tu), 3))
    cols = _first_cols(tu, [("dx_flange", "dy_flange", "dz_flange")])
    if cols is not None:
        d = np.nan_to_num(tu[list(cols)].to_numpy(dtype=float))
    ids = tu["target_id"].to_numpy()
    uniq = list(pd.unique(ids))
    tk = np.array([uniq.index(i) for i in ids], dtype=np.int64)
    _, _, r = fit_pin_and_targets(chain, q, d, tk, len(uniq))
    return pd.DataFrame(
        {
            "touchup_id": tu["touchup_id"].to_numpy(),
            "target_id": ids,
            "rx": r[:, 0],
            "ry": r[:, 1],
            "rz": r[:, 2],
            "norm": np.linalg.norm(r, axis=1),
        }
    )
