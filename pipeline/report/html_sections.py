"""The sections of ``report.html`` built from the fit's artefacts (:mod:`pipeline.report.html`).

Each builder takes the loaded run folder (:class:`pipeline.report.data.RunData`) and
returns the plain values its part of the template shows: the verdict (1), residuals
(2), targets and parameters (3), conditioning (4), cross-validation and the
error-model comparison (6), the run (7), in the numbering of :mod:`pipeline.report.html`
(whose page assembly adds the touch-up sections, 5, which need the recording's images).
:func:`pipeline.io.numfmt.fmt` is the template's number filter.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.io.numfmt import fmt, short
from pipeline.live.summary import from_metadata
from pipeline.report import plots
from pipeline.report.data import RunData, artefact_hashes, run_uuid
from pipeline.report.figures import (
    NOMINAL,
    accuracy_figures,
    chosen_model,
    crossval_summary,
    for_model,
    pin_positions,
    residual_groups,
    residual_norms,
    target_positions,
)

NA = "not available"


def verdict_section(data: RunData) -> dict[str, Any]:
    rec = data.recording or {}
    idf = data.identify or {}
    figs = accuracy_figures(data)
    groups = residual_groups(data)
    before = after = None
    for label, g in groups.items():
        n = residual_norms(g)
        if n is None or not len(n):
            continue
        rms = float(np.sqrt(np.nanmean(n * n)) * 1e3)
        mx = float(np.nanmax(n) * 1e3)
        if label == NOMINAL:
            before = (rms, mx)
        elif after is None:
            after = (rms, mx, label)
    scale_held = idf.get("scale_held")
    known = data.meta.get("known_distances", "")
    if scale_held is None and idf:
        scale_held = not bool(known)
    if scale_held:
        scale_text = (
            "The length scale was NOT identifiable: the recording carries no known distance "
            "between targets, so the robot's scale was held at the nominal model's. The figures "
            "below are shape accuracy (registration with scale); absolute accuracy needs a "
            "known distance (recording metadata known_distances or --distance)."
        )
    elif scale_held is False:
        scale_text = (
            f"The length scale was identified from the known distance(s) {known or '(given)'}."
        )
    else:
        scale_text = ""
    rpath = rec.get("path")
    from pipeline.accuracy.verdict import IMPROVED_BELOW, verdict

    tol = data.tolerance_mm
    # the nominal robot's error is identify.json's, as the console prints it; the report's
    # own nominal fit only where identify.json has none
    nominal = (idf.get("solver") or {}).get("initial_rms_mm")
    if not isinstance(nominal, (int, float)) and before:
        nominal = before[0]
    v = verdict(idf, tol, nominal_mm=nominal) or {}
    adequacy = (idf.get("trust") or {}).get("adequacy") or {}  # pipeline.stages.outliers.adequacy
    region = idf.get("region") or {}  # pipeline.estimation.region
    if before and isinstance(v.get("nominal_mm"), (int, float)):
        before = (float(v["nominal_mm"]), before[1])  # one nominal figure on the page
    validated = None
    if v.get("validated_mm") is not None:
        validated = (v["validated_mm"], v.get("validated_max_mm"), v["validated_how"])
    return {
        "robot": data.robot_name(),
        "recording": Path(rpath).name if rpath else NA,
        "recording_path": str(rpath) if rpath else "",
        "recording_reachable": data.recording_path() is not None,
        "date": data.date(),
        "model": chosen_model(data) or idf.get("error_model") or "",
        "before": before,
        "after": after,  # the shipped model's fit residual (training), shown as such
        "validated": validated,
        "predicted": v.get("predicted_mm"),
        "ratio": v.get("ratio"),
        "improved": v.get("improved"),
        "improved_below": IMPROVED_BELOW,
        "tolerance": short(tol),
        "tolerance_source": data.tolerance_source,
        "held_out": bool(validated and validated[2].startswith("held-out")),
        "passed": v.get("passed"),
        "verdict_line": v.get("line", ""),
        "lower_bound": bool(v.get("lower_bound")),
        "trust_warnings": v.get("warnings") or [],
        "adequacy_note": adequacy.get("note", ""),
        "adequacy_tested": bool(adequacy.get("tested")),
        "region_note": region.get("note", ""),
        "region_warn": bool(region.get("extrapolation_warning")),
        "figures": [
            {
                "label": f.label,
                "rms": fmt(f.rms_mm, 3),
                "max": fmt(f.max_mm, 3),
                "n": "" if f.n is None else str(f.n),
                "note": f.note,
            }
            for f in figs
        ],
        "scale_held": scale_held,
        "scale_text": scale_text,
        "n_images": rec.get("n_images"),
        "n_joint_states": rec.get("n_joint_states"),
        "truncated": bool(rec.get("truncated")),
        "measured": measurement_text(rec.get("measurement") or {}),
    }


def measurement_text(kv: dict[str, str]) -> str:
    """How a ``vtcal measure`` recording was measured, in words ("" when it does not say).

    ``kv`` is the recording's ``measurement`` metadata record as ingest kept it
    (:mod:`pipeline.live.summary`).
    """
    if not kv:
        return ""
    m = from_metadata(kv)
    gave = m.get("gave_up") or {}
    parts = [
        f"{m.get('converged', '?')} of {m.get('n_plan', '?')} planned touch-ups converged"
        + (" (gave up: " + ", ".join(f"{k} {v}" for k, v in gave.items()) + ")" if gave else ""),
        f"{m.get('captures', '?')} captures",
    ]
    cell_s = m.get("cell_s")
    if isinstance(cell_s, (int, float)):
        split = [(p, m.get(f"{p}_s")) for p in ("travel", "settle", "servo", "capture")]
        parts.append(
            f"measuring took {cell_s / 60:.1f} min of cell time"
            + (
                " (" + ", ".join(f"{p} {v:.0f} s" for p, v in split) + ")"
                if all(isinstance(v, (int, float)) for _, v in split)
                else ""
            )
        )
    if isinstance(m.get("sessions"), int) and m["sessions"] > 1:
        parts.append(f"over {m['sessions']} sessions (resumed)")
    return "by vtcal measure: " + "; ".join(parts)


def residual_section(data: RunData) -> dict[str, Any]:
    groups = residual_groups(data)
    hist = {}
    per_target: dict[str, list[np.ndarray]] = {}
    tids: list[str] = []
    if groups:
        all_t = sorted(
            {str(t) for g in groups.values() if "target_id" in g for t in g["target_id"]}
        )
        tids = all_t
        for label, g in groups.items():
            n = residual_norms(g)
            if n is None:
                continue
            hist[label] = n * 1e3
            if "target_id" in g and tids:
                per_target[label] = [
                    n[(g["target_id"].astype(str) == t).to_numpy()] * 1e3 for t in tids
                ]
    if not hist:
        # no residual table: rebuild the calibrated one from calibrated.urdf + targets
        tu = data.touchup_table()
        tp = target_positions(data)
        if tu is not None and tp:
            inl = tu[tu["inlier"].astype(bool)] if "inlier" in tu else tu
            p = pin_positions(data, inl)
            if p is not None:
                tgt = np.array([tp.get(int(t), np.full(3, np.nan)) for t in inl["target_id"]])
                n = np.linalg.norm(p - tgt, axis=1)
                hist["calibrated (recomputed)"] = n * 1e3
                tids = [str(t) for t in sorted(tp)]
                per_target["calibrated (recomputed)"] = [
                    n[(inl["target_id"].astype(str) == t).to_numpy()] * 1e3 for t in tids
                ]
    out: dict[str, Any] = {"available": bool(hist)}
    if hist:
        out["hist_svg"] = plots.residual_ecdf(hist, "residual distance (mm, log scale)")
        if per_target and tids:
            out["target_svg"] = plots.per_target(tids, per_target, "residual (mm)")
    return out


def targets_section(data: RunData) -> dict[str, Any]:
    df = data.targets
    if df is None or not len(df):
        return {"available": False}
    df = for_model(data, df)
    assert df is not None
    # a column with no value in any row (the print-shape fit's when it was not made) is not
    # shown: five columns of "-" pushed the table past the page; they are named below it
    empty = [str(c) for c in df.columns if c != "model" and not df[c].notna().any()]
    cols = [str(c) for c in df.columns if c != "model" and str(c) not in empty]

    def in_mm(c: str) -> bool:
        return (c in ("x", "y", "z") or c.startswith(("sigma", "std", "se_"))) and bool(
            pd.api.types.is_float_dtype(df[c])
        )

    shown = {c: (df[c] * 1e3 if in_mm(c) else df[c]).tolist() for c in cols}
    rows = [[fmt(shown[c][i], 3) for c in cols] for i in range(len(df))]
    headers = [f"{c} (mm)" if in_mm(c) else c for c in cols]
    tp = target_positions(data)
    svg = None
    if tp:
        pts = {"targets": np.array(list(tp.values()))}
        labels = {"targets": [str(k) for k in tp]}
        tu = data.touchup_table()
        if tu is not None:
            p = pin_positions(data, tu)
            if p is not None:
                pts["pin at touch-ups"] = p
        mm = {k: v * 1e3 for k, v in pts.items()}  # as the table beside it
        svg = plots.scatter_xy(mm, "x (mm)", "y (mm)", labels)
    return {"available": True, "headers": headers, "rows": rows, "svg": svg, "empty": empty}


PARAM_COLS = {
    "name": ("name", "parameter"),
    "value": ("value", "estimate"),
    "se": ("std", "std_error", "stderr", "sigma", "se"),
    "nominal": ("nominal",),
    "unit": ("unit",),
    "identifiable": ("identifiable", "identified"),
    "reason": ("held_reason", "reason", "why", "note"),
}


def parameters_section(data: RunData) -> dict[str, Any]:
    df = data.parameters
    idf = data.identify or {}
    chosen = chosen_model(data)
    per_model = (
        (idf.get("models") or {}).get(chosen) if isinstance(idf.get("models"), dict) else None
    )
    src = per_model if isinstance(per_model, dict) else idf
    unid = (
        src.get("held") or src.get("unidentifiable") or src.get("unidentifiable_parameters") or []
    )
    out: dict[str, Any] = {"available": df is not None and len(df) > 0, "unidentifiable": []}
    if isinstance(unid, dict):
        out["unidentifiable"] = [{"name": str(k), "why": str(v)} for k, v in unid.items()]
    elif isinstance(unid, list):
        for u in unid:
            if isinstance(u, dict):
                out["unidentifiable"].append(
                    {"name": str(u.get("name", u)), "why": str(u.get("reason", u.get("why", "")))}
                )
            else:
                out["unidentifiable"].append({"name": str(u), "why": ""})
    groups: dict[str, list[str]] = {}
    for u in out["unidentifiable"]:
        groups.setdefault(u["why"] or "held at nominal", []).append(u["name"])
    out["unid_groups"] = [{"why": k, "names": v} for k, v in groups.items()]
    if df is None or not len(df):
        return out
    models = None
    mcol = next((c for c in ("model", "error_model") if c in df.columns), None)
    if mcol is not None:
        models = [str(m) for m in pd.unique(df[mcol])]
        if chosen in models:
            df = df[df[mcol] == chosen]
        else:
            df = df[df[mcol] == models[0]]
    pick = {k: next((c for c in opts if c in df.columns), None) for k, opts in PARAM_COLS.items()}
    rows = []
    for _, r in df.iterrows():
        unit = str(r[pick["unit"]]) if pick["unit"] else ""
        scale = 1e3 if unit == "m" else (180.0 / math.pi if unit == "rad" else 1.0)
        shown_unit = {"m": "mm", "rad": "deg"}.get(unit, unit)

        def val(key: str, r: Any = r, scale: float = scale) -> str:
            c = pick[key]
            if c is None:
                return ""
            v = r[c]
            if isinstance(v, (float, int, np.floating, np.integer)) and not isinstance(v, bool):
                return fmt(float(v) * scale, 4)
            return fmt(v)

        ident = r[pick["identifiable"]] if pick["identifiable"] else True
        rows.append(
            {
                "name": str(r[pick["name"]]) if pick["name"] else "",
                "value": val("value"),
                "se": val("se"),
                "nominal": val("nominal"),
                "unit": shown_unit,
                "identifiable": bool(ident) if ident is not None else True,
                "reason": str(r[pick["reason"]])
                if pick["reason"] and pd.notna(r[pick["reason"]])
                else "",
            }
        )
    out.update(
        rows=[r for r in rows if r["identifiable"]],
        n_held=sum(1 for r in rows if not r["identifiable"]),
        has_nominal=pick["nominal"] is not None,
        models=models,
        shown_model=str(df[mcol].iloc[0]) if mcol else "",
    )
    return out


#: identify.json fields shown in the summary, with their labels (the rest is in the raw dump)
SUMMARY_FIELDS = (
    ("model_description", "error model"),
    ("n_rows", "touch-ups in the table"),
    ("n_used", "touch-ups used"),
    ("n_targets", "targets"),
    ("n_params", "kinematic parameters of the model"),
    ("n_identified", "parameters identified"),
    ("dof", "degrees of freedom (redundancy)"),
    ("sigma_mm", "residual standard deviation (mm)"),
    ("scale_note", "length scale"),
    ("conditioning_note", "conditioning"),
    ("base_note", "base frame"),
)


def conditioning_section(data: RunData) -> dict[str, Any]:
    idf = data.identify or {}
    if not idf:
        return {"available": False}
    facts = []
    for key, label in (
        ("cond", "condition number (scaled identification Jacobian)"),
        ("condition_number", "condition number"),
        ("rank", "rank"),
    ):
        if key in idf and not isinstance(idf[key], (dict, list)):
            facts.append((label, fmt(idf[key], 4)))
    obs = idf.get("observability") or {}
    obs_rows = []
    if isinstance(obs, dict):
        for k in sorted(obs):
            obs_rows.append((k, fmt(obs[k], 4)))
    for k in ("O1", "O2", "O3", "O4", "O5"):
        if k in idf and not any(r[0] == k for r in obs_rows):
            obs_rows.append((k, fmt(idf[k], 4)))
    sv = idf.get("singular_values")
    svg = None
    if isinstance(sv, list) and len(sv) > 1:
        try:
            svg = plots.singular_values(np.asarray(sv, dtype=float))
        except (TypeError, ValueError):
            svg = None
    summary = [(label, fmt(idf[k], 4)) for k, label in SUMMARY_FIELDS if k in idf]
    pin = idf.get("p_flange_pin")
    if isinstance(pin, list) and len(pin) == 3:
        summary.append(
            (
                "virtual pin in the flange frame (mm)",
                ", ".join(fmt(float(v) * 1e3, 3) for v in pin),
            )
        )
    for d in idf.get("distances") or []:
        if isinstance(d, dict):
            summary.append(
                (
                    f"known distance {d.get('a')}-{d.get('b')} (mm)",
                    f"given {fmt(float(d.get('metres', 'nan')) * 1e3, 3)}, "
                    f"fitted {fmt(float(d.get('fitted_metres', 'nan')) * 1e3, 3)}",
                )
            )
    solver = idf.get("solver")
    if isinstance(solver, dict):  # scipy's own words stay in identify.json's solver.message
        summary.append(
            (
                "solver",
                f"{solver_status(solver)} ({solver.get('method', '')}, "
                f"{solver.get('nfev', '?')} evaluations)",
            )
        )
    raw = json.dumps(idf, indent=1, sort_keys=True, default=str)
    return {
        "available": True,
        "facts": facts,
        "observability": obs_rows,
        "svg": svg,
        "summary": summary,
        "raw": raw,
    }


#: ``scipy.optimize.least_squares`` status -> how the solve ended, in words
SOLVER_STATUS = {
    -1: "failed (improper input)",
    0: "stopped: evaluation limit reached, not converged",
    1: "converged (gradient small)",
    2: "converged (cost change small)",
    3: "converged (step small)",
    4: "converged (cost change and step small)",
}


def solver_status(solver: dict[str, Any]) -> str:
    """How identify.json's ``solver`` ended, in a few words (scipy's message is kept there)."""
    try:
        return SOLVER_STATUS[int(solver["status"])]
    except (KeyError, TypeError, ValueError):
        message = str(solver.get("message") or "").strip()
        return message or "unknown"


def _models_section(data: RunData) -> list[dict[str, str]]:
    """Error-model comparison from identify.json ``models`` (fit and predicted figures)."""
    idf = data.identify or {}
    models = idf.get("models")
    if not isinstance(models, dict):
        return []
    chosen = chosen_model(data)
    rows = []
    for name, m in models.items():
        if not isinstance(m, dict):
            continue
        rows.append(
            {
                "model": str(name),
                "chosen": "yes" if name == chosen else "",
                "description": str(m.get("model_description", "")),
                "identified": f"{m.get('n_identified', '?')}/{m.get('n_params', '?')}",
                "rms": fmt(m.get("rms_mm")),
                "max": fmt(m.get("max_mm")),
                "pred": fmt(m.get("predicted_shape_rms_mm", m.get("predicted_rms_mm"))),
                "cond": fmt(m.get("cond"), 4),
            }
        )
    return rows


def crossval_section(data: RunData) -> dict[str, Any]:
    rows = crossval_summary(data)
    models = _models_section(data)
    cv = (data.identify or {}).get("crossval")
    cv = cv if isinstance(cv, dict) else {}
    chosen = cv.get("chosen_model") or chosen_model(data)
    if not rows:
        return {"available": False, "models": models}
    labels = [r["model"] for r in rows]
    series = {"k-fold RMS": [r["kfold_rms_mm"] for r in rows]}
    if any(r["loto_n"] for r in rows):
        series["leave-one-target-out RMS"] = [r["loto_rms_mm"] for r in rows]
    svg = plots.bars(labels, series, "held-out error (mm)")
    train = {}
    for name, m in (cv.get("models") or {}).items():
        if isinstance(m, dict):
            train[str(name)] = m.get("train_rms_mm")

    def scored(r: dict[str, Any], scheme: str) -> str:
        extra = r[f"{scheme}_unscored"]
        return f"{r[f'{scheme}_n']}" + (f" (+{extra} not scored)" if extra else "")

    return {
        "available": True,
        "svg": svg,
        "rows": [
            {
                "model": r["model"],
                "chosen": r["model"] == chosen,
                "train": fmt(train.get(r["model"])),
                "kfold": f"{fmt(r['kfold_rms_mm'])} / {fmt(r['kfold_max_mm'])}",
                "kfold_n": scored(r, "kfold"),
                "loto": (
                    f"{fmt(r['loto_rms_mm'])} / {fmt(r['loto_max_mm'])}" if r["loto_n"] else "–"
                ),
                "loto_n": scored(r, "loto"),
            }
            for r in rows
        ],
        "choice": str(cv.get("choice", "")),
        "note": str(cv.get("note", "")),
        "models": models,
    }


def run_section(data: RunData) -> dict[str, Any]:
    rec = data.recording or {}
    run = data.run or {}
    stages = []
    for s in run.get("stages", []) if isinstance(run.get("stages"), list) else []:
        if isinstance(s, dict):
            stages.append(
                {
                    "stage": s.get("stage", ""),
                    "status": s.get("status", ""),
                    "seconds": fmt(s.get("seconds"), 2),
                    "outputs": ", ".join(map(str, s.get("outputs", []))),
                    "note": s.get("note", ""),
                }
            )
    inferred = rec.get("inferred") or {}
    if isinstance(inferred, list):
        inferred = {str(k): "" for k in inferred}
    # ingest fills what the recording did not declare into its metadata (the later stages
    # read it there): listed once, as inferred, with how it was found
    declared = {k: v for k, v in data.meta.items() if k not in inferred}
    return {
        "stages": stages,
        "metadata": sorted(declared.items()),
        "inferred": sorted((str(k), str(v)) for k, v in inferred.items()),
        "warnings": [str(w) for w in rec.get("warnings", []) or []],
        "problems": data.problems,
        "hashes": sorted(artefact_hashes(data.run_dir).items()),
        "run_id": run_uuid(data.run_dir),
        "version": __version__,
        "joint_names": data.joint_names,
        "base_link": data.base_link or NA,
        "flange_link": data.flange_link or NA,
        "image_topic": rec.get("image_topic") or NA,
    }
