"""A batch's summary table (``summary.parquet``/``.csv``) and its comparison across runs."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.batch.outcome import RecordingOutcome, internal_error_line, one_line
from pipeline.errors import VtcalError

if TYPE_CHECKING:
    import pandas as pd

    from pipeline.run.orchestrator import RunConfig


def _summary_columns() -> tuple[list[str], list[str]]:
    """Columns of the summary and the nullable ones, from ``schemas/batch_summary.json``."""
    from pipeline.io.artefacts import load_schema

    schema = load_schema("batch_summary")
    return schema.column_names, [c.name for c in schema.columns if c.nullable]


def summary_table(outcomes: Sequence[RecordingOutcome]) -> pd.DataFrame:
    """One row per recording, columns of ``schemas/batch_summary.json``."""
    import pandas as pd

    rows = []
    for o in outcomes:
        f = o.figures
        rows.append(
            {
                "name": o.name,
                "recording": o.recording,
                "run_dir": o.run_dir,
                "robot": o.robot or o.robot_urdf,
                "robot_urdf": o.robot_urdf,
                "notes": o.notes,
                "status": o.status,
                "error_kind": o.error_kind,
                "error": o.error,
                "exit_code": int(o.exit_code),
                "stages": " ".join(f"{s}:{st}" for s, st, _ in o.stages),
                "stages_ran": sum(st == "ran" for _, st, _ in o.stages),
                "stages_cached": sum(st == "cached" for _, st, _ in o.stages),
                "seconds": float(o.seconds),
                "cpu_seconds": float(o.cpu_seconds),
                "peak_rss_mb": o.peak_rss_mb,
                "worker": o.worker,
                "model": f.get("model"),
                "n_touchups": f.get("n_rows"),
                "n_used": f.get("n_used"),
                "n_targets": f.get("n_targets"),
                "n_identified": f.get("n_identified"),
                "n_params": f.get("n_params"),
                "verdict": o.verdict,
                "validated_mm": f.get("validated_mm"),
                "validated_how": f.get("validated_how"),
                "nominal_mm": f.get("nominal_mm"),
                "tolerance_mm": f.get("tolerance_mm"),
                "rms_mm": f.get("rms_mm"),
                "max_mm": f.get("max_mm"),
                "predicted_shape_rms_mm": f.get("predicted_shape_rms_mm"),
                "predicted_absolute_rms_mm": f.get("predicted_absolute_rms_mm"),
                "cond": f.get("cond"),
                "scale_identified": f.get("scale_identified"),
                "headline": " | ".join(o.headline),
                "retried": bool(o.retried),
            }
        )
    columns, nullable = _summary_columns()
    df = pd.DataFrame(rows, columns=columns)
    for c in nullable:  # keep None (not NaN) so ints stay ints and bools stay bools
        df[c] = pd.Series([r[c] for r in rows], dtype=object)
    return df


def write_summary(
    out_dir: Path,
    summary: pd.DataFrame,
    *,
    config: RunConfig | None = None,
    until: str | None = None,
    force: bool = False,
) -> Path:
    """Write ``out_dir/summary.parquet`` (schema ``batch_summary``); return its path."""
    from pipeline.io.artefacts import write_artefact
    from pipeline.run.orchestrator import jsonable

    path = out_dir / "summary.parquet"
    write_artefact(
        path,
        summary,
        "batch_summary",
        stage="batch",
        config={"until": until, "force": force, "run": jsonable(config)},
        inputs={},
        extra_meta={"recordings": json.dumps(list(summary["recording"]) if len(summary) else [])},
    )
    return path


def compare_batch(out_dir: Path, outcomes: Sequence[RecordingOutcome]) -> tuple[Any, str]:
    """The cross-run table (``vtcal compare``) of the identified runs of a batch.

    Writes ``out_dir/compare.parquet`` (schema ``compare``) and
    ``out_dir/compare.html`` as ``vtcal compare`` does, for the runs that finished
    with identify (ran or cached), in batch order (the first run of each robot is
    the drift baseline).

    Returns
    -------
    (CompareResult or None, note): None with the reason when there is nothing to
    compare or :mod:`pipeline.accuracy.compare` is absent or fails (the batch summary stands
    alone; a comparison failure never fails the batch).
    """
    runs = identified_runs(outcomes)
    if not runs:
        return None, "no identified run to compare"
    try:
        from pipeline.accuracy.compare import compare_runs, render_html
    except ImportError:
        return None, "cross-run comparison not available (pipeline.accuracy.compare missing)"
    from pipeline.io.artefacts import atomic_write_bytes, write_artefact

    try:
        res = compare_runs(runs)
        write_artefact(
            out_dir / "compare.parquet",
            res.table,
            "compare",
            stage="compare",
            config={"k_sigma": res.summary.get("k_sigma")},
            inputs={},
            extra_meta={"runs": ",".join(res.summary.get("runs", []))},
        )
        atomic_write_bytes(out_dir / "compare.html", render_html(res).encode())
    except VtcalError as exc:
        return None, f"comparison failed: {one_line(str(exc))}"
    except Exception as exc:  # a bug there must not cost the batch its summary
        return None, f"comparison failed: internal error: {internal_error_line(exc)}"
    return res, f"{out_dir / 'compare.parquet'}, {out_dir / 'compare.html'}"


def identified_runs(outcomes: Sequence[RecordingOutcome]) -> list[Path]:
    return [Path(o.run_dir) for o in outcomes if o.status == "ok" and o.figures]


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    return format(v, spec)


def compare_lines(res: Any) -> list[str]:
    """The printed lines of a :class:`pipeline.accuracy.compare.CompareResult`: the shipped
    model's line per run, the verdict and the drift flags (every model is in compare.html).

    Stored in ``batch.json`` so that an unchanged batch prints them without
    rebuilding the comparison.
    """
    from pipeline.accuracy.compare import heldout_text

    lines = ["cross-run comparison (vtcal compare), shipped model:"]
    for r in res.runs.itertuples():
        if not r.shipped:
            continue
        lines.append(
            f"  {r.run:<20} {r.model:<8} held-out {heldout_text(r.heldout_rms_mm)}  "
            f"training {_fmt(r.train_rms_mm, '.4f')} mm  cond {_fmt(r.cond, '.3g')}  "
            f"rejected {r.n_rejected}"
        )
    lines.append(f"  {res.summary.get('verdict', '')}")
    moved = res.moved
    if len(moved):
        shipped = {(r.run, r.model) for r in res.runs.itertuples() if r.shipped}
        for (run, model), g in moved.groupby(["run", "model"], sort=False):
            if (run, model) not in shipped:
                continue
            top = g.reindex(g["delta_sigma"].abs().sort_values(ascending=False).index)
            names = ", ".join(str(p) for p in top["parameter"].head(3))
            lines.append(
                f"    {run} [{model}] against {g['baseline_run'].iloc[0]}: {len(g)} parameter(s) "
                f"moved (largest: {names})"
            )
    return lines
