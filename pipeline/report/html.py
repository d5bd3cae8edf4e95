"""``report.html``: the accuracy report of a run, one self-contained file.

Built only from the artefacts of a run folder (:func:`pipeline.report.data.load_run`),
so ``vtcal report RUN_DIR`` re-renders it without re-solving and without the
recording. Layout (template ``reports/report.html.j2``, jinja2 with autoescape):

1. the verdict: accuracy before and after (mm: RMS, max; predicted and
   cross-validated where the run has them), the robot, the recording, the
   date (from the recording's stamps, so the file is deterministic), whether
   the length scale was identified;
2. residuals: their cumulative distribution per model (log scale) and per target;
3. parameters with standard errors, and what was not identifiable and why;
4. conditioning and observability;
5. touch-ups: every rejected one with its reason and, when the recording is
   still reachable, a thumbnail with the fitted ellipse; e_T convergence;
6. cross-validation and the error-model comparison;
7. the run: stages, timings, inferred settings, warnings.

Everything is inline (CSS, SVG plots, PNG thumbnails as ``data:`` URIs) and a
Content-Security-Policy forbids any request, so the file opens offline.

The sections built from the fit's artefacts (1-4, 6, 7) are in
:mod:`pipeline.report.html_sections`; this module has the touch-up sections (5,
with the recording's images) and the page assembly.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.io.artefacts import atomic_write_bytes
from pipeline.io.run_folder import RUN_FILES
from pipeline.report import plots
from pipeline.report.data import RunData, load_run
from pipeline.report.diagnosis import camera_section
from pipeline.report.html_sections import (
    NA,
    conditioning_section,
    crossval_section,
    fmt,
    parameters_section,
    residual_section,
    run_section,
    targets_section,
    verdict_section,
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


# ------------------------------------------------------------------ touch-up sections


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


# ------------------------------------------------------------------ entry


def report_context(data: RunData, images: dict[int, np.ndarray] | None) -> dict[str, Any]:
    """Everything the template shows (pure: artefacts and images in, plain values out)."""
    return {
        "verdict": verdict_section(data),
        "residuals": residual_section(data),
        "targets": targets_section(data),
        "parameters": parameters_section(data),
        "conditioning": conditioning_section(data),
        "touchups": _touchup_section(data, images),
        "convergence": _convergence_section(data),
        "crossval": crossval_section(data),
        "camera": camera_section(data),
        "run": run_section(data),
        "NA": NA,
    }


def render(context: dict[str, Any]) -> str:
    """Render the report template with a context from :func:`report_context`."""
    return render_template(TEMPLATE, fmt, **context)


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
    if data.touchup_table() is None:
        return None
    from pipeline.report.images import grey_images, recording_frames

    thumbs = thumbnail_frames(data)
    frames = recording_frames(data, thumbs)
    return None if frames is None else grey_images(frames, thumbs)


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
    out_path : destination (default ``run_dir / RUN_FILES["report"]``)
    tolerance_mm : the PASS/FAIL tolerance (default: run.json's, else the recording's key)
    data, images : the run folder already loaded (:func:`load_run`) and the thumbnails'
        images (:func:`thumbnail_frames`), when the caller has them (one load and one pass
        over the recording for both outputs: :func:`pipeline.report.outputs.build_outputs`)

    Sections whose artefacts are missing say "not available". Images are read
    again from the recording only if the path in ``recording.json`` exists.
    """
    run_dir = Path(run_dir)
    out = Path(out_path) if out_path is not None else run_dir / RUN_FILES["report"]
    loaded = data is not None
    data = data if data is not None else load_run(run_dir)
    if tolerance_mm is not None:
        data = copy.copy(data)
        data.run = {**(data.run or {}), "tolerance_mm": tolerance_mm}
    html = render(report_context(data, images if loaded else _report_images(data)))
    atomic_write_bytes(out, html.encode("utf-8"), mode=0o644)  # a report is for sharing
    return out
