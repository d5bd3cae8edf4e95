"""``report.html``: the accuracy report of a run, one self-contained file.

Built only from the artefacts of a run folder (:func:`pipeline.report.data.load_run`),
so ``vtcal report RUN_DIR`` re-renders it without re-solving and without the
recording. Layout (template ``reports/report.html.j2``, jinja2 with autoescape):

1. the verdict: accuracy before and after (mm: RMS, max; predicted and
   cross-validated where the run has them), the robot, the recording, the
   date (from the recording's stamps, so the file is deterministic), whether
   the length scale was identified;
2. residuals: histograms before/after and per target;
3. parameters with standard errors, and what was not identifiable and why;
4. conditioning and observability;
5. touch-ups: every rejected one with its reason and, when the recording is
   still reachable, a thumbnail with the fitted ellipse; e_T convergence;
6. cross-validation and the error-model comparison;
7. the run: stages, timings, inferred settings, warnings.

Everything is inline (CSS, SVG plots, PNG thumbnails as ``data:`` URIs) and a
Content-Security-Policy forbids any request, so the file opens offline.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.artefacts import atomic_write_bytes
from pipeline.measure.summary import from_metadata
from pipeline.report import plots
from pipeline.report.data import RunData, artefact_hashes, load_run, run_uuid
from pipeline.report.diagnosis import camera_section
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
from pipeline.report.templates import render_template
from pipeline.report.touchup_views import (
    convergence_traces,
    designated,
    detection_ellipse,
    touchup_frames,
)

TEMPLATE = "report.html.j2"
#: at most this many thumbnails / convergence traces (keeps the file small)
MAX_THUMBS = 40
#: at most this many bytes of thumbnails in the page (keeps it well under 5 MB)
THUMB_BUDGET = 2_500_000
MAX_TRACES = 60
NA = "not available"


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        f = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(f):
        return "–"
    if f != 0 and (abs(f) < 1e-3 or abs(f) >= 1e5):
        return f"{f:.{digits}g}"
    return f"{f:.{digits}f}"


# ------------------------------------------------------------------ sections


def _verdict(data: RunData) -> dict[str, Any]:
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
    from pipeline.verdict import IMPROVED_BELOW, verdict

    tol = data.tolerance_mm
    v = verdict(idf, tol, nominal_mm=before[0] if before else None) or {}
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
        "tolerance": tol,
        "passed": v.get("passed"),
        "verdict_line": v.get("line", ""),
        "figures": [
            {
                "label": f.label,
                "rms": _fmt(f.rms_mm, 3),
                "max": _fmt(f.max_mm, 3),
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
    (:mod:`pipeline.measure.summary`).
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
        parts.append(f"measuring took {cell_s / 60:.1f} min of cell time")
    if isinstance(m.get("sessions"), int) and m["sessions"] > 1:
        parts.append(f"over {m['sessions']} sessions (resumed)")
    return "by vtcal measure: " + "; ".join(parts)


def _residual_section(data: RunData) -> dict[str, Any]:
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
        out["hist_svg"] = plots.histogram(hist, "residual distance (mm)")
        if per_target and tids:
            out["target_svg"] = plots.per_target(tids, per_target, "residual (mm)")
    return out


def _targets_section(data: RunData) -> dict[str, Any]:
    df = data.targets
    if df is None or not len(df):
        return {"available": False}
    df = for_model(data, df)
    assert df is not None
    cols = [str(c) for c in df.columns if c != "model"]

    def in_mm(c: str) -> bool:
        return (c in ("x", "y", "z") or c.startswith(("sigma", "std", "se_"))) and bool(
            pd.api.types.is_float_dtype(df[c])
        )

    shown = {c: (df[c] * 1e3 if in_mm(c) else df[c]).tolist() for c in cols}
    rows = [[_fmt(shown[c][i], 3) for c in cols] for i in range(len(df))]
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
        svg = plots.scatter_xy(pts, "x (m)", "y (m)", labels)
    return {"available": True, "headers": headers, "rows": rows, "svg": svg}


PARAM_COLS = {
    "name": ("name", "parameter"),
    "value": ("value", "estimate"),
    "se": ("std", "std_error", "stderr", "sigma", "se"),
    "nominal": ("nominal",),
    "unit": ("unit",),
    "identifiable": ("identifiable", "identified"),
    "reason": ("held_reason", "reason", "why", "note"),
}


def _parameters_section(data: RunData) -> dict[str, Any]:
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
                return _fmt(float(v) * scale, 4)
            return _fmt(v)

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


def _conditioning_section(data: RunData) -> dict[str, Any]:
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
            facts.append((label, _fmt(idf[key], 4)))
    obs = idf.get("observability") or {}
    obs_rows = []
    if isinstance(obs, dict):
        for k in sorted(obs):
            obs_rows.append((k, _fmt(obs[k], 4)))
    for k in ("O1", "O2", "O3", "O4", "O5"):
        if k in idf and not any(r[0] == k for r in obs_rows):
            obs_rows.append((k, _fmt(idf[k], 4)))
    sv = idf.get("singular_values")
    svg = None
    if isinstance(sv, list) and len(sv) > 1:
        try:
            svg = plots.singular_values(np.asarray(sv, dtype=float))
        except (TypeError, ValueError):
            svg = None
    summary = [(label, _fmt(idf[k], 4)) for k, label in SUMMARY_FIELDS if k in idf]
    pin = idf.get("p_flange_pin")
    if isinstance(pin, list) and len(pin) == 3:
        summary.append(
            (
                "virtual pin in the flange frame (mm)",
                ", ".join(_fmt(float(v) * 1e3, 3) for v in pin),
            )
        )
    for d in idf.get("distances") or []:
        if isinstance(d, dict):
            summary.append(
                (
                    f"known distance {d.get('a')}-{d.get('b')} (mm)",
                    f"given {_fmt(float(d.get('metres', 'nan')) * 1e3, 3)}, "
                    f"fitted {_fmt(float(d.get('fitted_metres', 'nan')) * 1e3, 3)}",
                )
            )
    solver = idf.get("solver")
    if isinstance(solver, dict):
        summary.append(
            (
                "solver",
                f"{solver.get('method', '')}, {solver.get('message', '')} "
                f"({solver.get('nfev', '?')} evaluations)",
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
                "rms": _fmt(m.get("rms_mm")),
                "max": _fmt(m.get("max_mm")),
                "pred": _fmt(m.get("predicted_shape_rms_mm", m.get("predicted_rms_mm"))),
                "cond": _fmt(m.get("cond"), 4),
            }
        )
    return rows


def _touchup_section(data: RunData, images: dict[int, np.ndarray] | None) -> dict[str, Any]:
    from pipeline.report.images import annotate, png_data_uri

    tu = data.touchup_table()
    if tu is None:
        return {"available": False}
    inl = tu["inlier"].astype(bool) if "inlier" in tu else pd.Series(True, index=tu.index)
    conv = tu["converged"].astype(bool) if "converged" in tu else inl
    frames = touchup_frames(data)
    d0 = designated(data)
    rejected = []
    budget = THUMB_BUDGET
    n_over = 0
    for _, r in tu[~inl].iterrows():
        tid = int(r["touchup_id"])
        fr = frames.get(tid, [])
        thumb = None
        if images is not None and fr and fr[-1] in images:
            ell = detection_ellipse(data, fr[-1])
            uri = png_data_uri(annotate(images[fr[-1]], ell, d0[:2] if d0 else None))
            if len(uri) <= budget:
                thumb, budget = uri, budget - len(uri)
            else:
                n_over += 1
        rejected.append(
            {
                "id": tid,
                "target": str(r.get("target_id", "")),
                "reason": r["reason"] or "rejected",
                "converged": bool(r.get("converged", False)),
                "frame": fr[-1] if fr else None,
                "thumb": thumb,
            }
        )
    return {
        "available": True,
        "n": len(tu),
        "n_converged": int(conv.sum()),
        "n_inliers": int(inl.sum()),
        "n_rejected": int((~inl).sum()),
        "n_targets": int(tu["target_id"].nunique()) if "target_id" in tu else None,
        "rejected": rejected,
        "images_note": (
            "Thumbnails are not shown: the recording named in recording.json is not reachable."
            if images is None
            else (f"{n_over} thumbnail(s) left out to keep the file small." if n_over else "")
        ),
    }


def _convergence_section(data: RunData) -> dict[str, Any]:
    tr = convergence_traces(data)
    if not tr:
        return {"available": False}
    keys = sorted(tr)[:MAX_TRACES]
    m = data.meta

    def f(k: str) -> float | None:
        try:
            return float(m[k])
        except (KeyError, ValueError):
            return None

    svg = plots.convergence(
        {f"#{k}": tr[k] for k in keys},
        [f("threshold_px"), f("threshold_px"), f("threshold_size_px")],
        ["px", "px", "px"],
    )
    iters = [len(tr[k]) for k in keys]
    return {
        "available": True,
        "svg": svg,
        "n": len(tr),
        "shown": len(keys),
        "median_iters": float(np.median(iters)) if iters else None,
        "max_iters": max(iters) if iters else None,
    }


def _crossval_section(data: RunData) -> dict[str, Any]:
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
                "train": _fmt(train.get(r["model"])),
                "kfold": f"{_fmt(r['kfold_rms_mm'])} / {_fmt(r['kfold_max_mm'])}",
                "kfold_n": scored(r, "kfold"),
                "loto": (
                    f"{_fmt(r['loto_rms_mm'])} / {_fmt(r['loto_max_mm'])}" if r["loto_n"] else "–"
                ),
                "loto_n": scored(r, "loto"),
            }
            for r in rows
        ],
        "choice": str(cv.get("choice", "")),
        "note": str(cv.get("note", "")),
        "models": models,
    }


def _run_section(data: RunData) -> dict[str, Any]:
    rec = data.recording or {}
    run = data.run or {}
    stages = []
    for s in run.get("stages", []) if isinstance(run.get("stages"), list) else []:
        if isinstance(s, dict):
            stages.append(
                {
                    "stage": s.get("stage", ""),
                    "status": s.get("status", ""),
                    "seconds": _fmt(s.get("seconds"), 2),
                    "outputs": ", ".join(map(str, s.get("outputs", []))),
                    "note": s.get("note", ""),
                }
            )
    inferred = rec.get("inferred") or {}
    if isinstance(inferred, list):
        inferred = {str(k): "" for k in inferred}
    return {
        "stages": stages,
        "metadata": sorted(data.meta.items()),
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


# ------------------------------------------------------------------ entry


def report_context(data: RunData, images: dict[int, np.ndarray] | None) -> dict[str, Any]:
    """Everything the template shows (pure: artefacts and images in, plain values out)."""
    return {
        "verdict": _verdict(data),
        "residuals": _residual_section(data),
        "targets": _targets_section(data),
        "parameters": _parameters_section(data),
        "conditioning": _conditioning_section(data),
        "touchups": _touchup_section(data, images),
        "convergence": _convergence_section(data),
        "crossval": _crossval_section(data),
        "camera": camera_section(data),
        "run": _run_section(data),
        "NA": NA,
    }


def render(context: dict[str, Any]) -> str:
    """Render the report template with a context from :func:`report_context`."""
    return render_template(TEMPLATE, _fmt, **context)


def thumbnail_frames(data: RunData) -> list[int]:
    """Frame indices of the images the page shows: the rejected touch-ups' last captures."""
    tu = data.touchup_table()
    if tu is None:
        return []
    inl = tu["inlier"].astype(bool) if "inlier" in tu else pd.Series(True, index=tu.index)
    frames = touchup_frames(data)
    want = [frames[t][-1] for t in tu.loc[~inl, "touchup_id"].astype(int) if frames.get(t)]
    return want[:MAX_THUMBS]


def _report_images(data: RunData) -> dict[int, np.ndarray] | None:
    """Images of the rejected touch-ups' last captures, if the recording is reachable."""
    path = data.recording_path()
    if path is None or data.touchup_table() is None:
        return None
    from pipeline.report.images import load_frames

    image_topic = (data.recording or {}).get("image_topic")
    return load_frames(path, image_topic, thumbnail_frames(data))


def build_report(
    run_dir: Path,
    out_path: Path | None = None,
    tolerance_mm: float | None = None,
    *,
    data: RunData | None = None,
    images: dict[int, np.ndarray] | None = None,
) -> Path:
    """Write ``report.html`` of a run folder from its artefacts; return its path.

    Parameters
    ----------
    run_dir : the run folder (``vtcal run --out``)
    out_path : destination (default ``run_dir / "report.html"``)
    tolerance_mm : the PASS/FAIL tolerance (default: run.json's, else the recording's key)
    data, images : the run folder already loaded (:func:`load_run`) and the thumbnails'
        images (:func:`thumbnail_frames`), when the caller has them (one load and one pass
        over the recording for both outputs: :func:`pipeline.report.outputs.build_outputs`)

    Sections whose artefacts are missing say "not available". Images are read
    again from the recording only if the path in ``recording.json`` exists.
    """
    run_dir = Path(run_dir)
    out = Path(out_path) if out_path is not None else run_dir / "report.html"
    loaded = data is not None
    data = data if data is not None else load_run(run_dir)
    if tolerance_mm is not None:
        data = copy.copy(data)
        data.run = {**(data.run or {}), "tolerance_mm": tolerance_mm}
    html = render(report_context(data, images if loaded else _report_images(data)))
    atomic_write_bytes(out, html.encode("utf-8"))
    out.chmod(0o644)  # a report is for sharing (the temporary file was private)
    return out
