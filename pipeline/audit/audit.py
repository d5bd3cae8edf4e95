"""The audit as one pure function: run folders' contents in, three tables out.

For each robot's history (:func:`pipeline.audit.identity.histories`), oldest first:

1. every recording is calibrated on its own (:func:`pipeline.audit.fit.fit_item`);
2. from the second on, the previous calibration is validated on it and its
   drift measured (:func:`pipeline.audit.drift.validate_previous`);
3. consecutive calibrations are tested for a change (:mod:`pipeline.audit.change`)
   and a change read as one physical cause (:mod:`pipeline.audit.attribute`);
4. robots of one model are compared with each other (the first recording of
   each against the previous robot's): "different robots" is what they should read;
5. the error models are ranked across every recording (:mod:`pipeline.audit.fleet`).

Tables (``schemas/audit_recordings.json``, ``audit_changes.json``, ``audit_models.json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.audit.attribute import Reading, attribute
from pipeline.audit.change import ALPHA, compare_estimates
from pipeline.audit.drift import TOLERANCE_MM, read_drift_m, validate_previous
from pipeline.audit.fit import Estimate, fit_item
from pipeline.audit.fleet import MODELS, model_matrix, ranking
from pipeline.audit.identity import AuditItem, histories


@dataclass
class AuditResult:
    """The audit's tables and its summary lines."""

    recordings: pd.DataFrame
    changes: pd.DataFrame
    models: pd.DataFrame
    ranking: pd.DataFrame
    lines: list[str] = field(default_factory=list)
    estimates: dict[str, Estimate] = field(default_factory=dict, repr=False)


def significance(changed: bool, kind: str, read_mm: float, tolerance_mm: float) -> str:
    """``none``, ``within_tolerance`` or ``beyond_tolerance`` of one comparison.

    A change the test sees (``changed``) whose read drift (the pin's RMS move over the
    later recording's poses, :func:`pipeline.audit.drift.read_drift_m`) is at most the
    tolerance is *detectable, within tolerance*: real, and not worth a page. Without a
    drift figure (NaN) or read as different robots, it matters.
    """
    if not changed:
        return "none"
    if kind != "different_robot" and np.isfinite(read_mm) and read_mm <= tolerance_mm:
        return "within_tolerance"
    return "beyond_tolerance"


def _change_row(
    kind: str,
    a: AuditItem,
    b: AuditItem,
    ea: Estimate,
    eb: Estimate,
    alpha: float,
    tolerance_mm: float = TOLERANCE_MM,
) -> dict[str, Any]:
    diff = compare_estimates(ea, eb)
    reading = attribute(diff, eb, alpha) if diff.changed(alpha) else Reading("none", "", "")
    read_mm = read_drift_m(eb, diff, reading) * 1e3
    sig = significance(diff.changed(alpha), reading.kind, read_mm, tolerance_mm)
    if not reading.text:
        reading.text = (
            f"no change: chi2 {diff.T:.1f} on {diff.dof} dof{_f_text(diff.f_dof)} "
            f"(p = {diff.p:.2g} >= {alpha:g})"
        )
    elif sig == "within_tolerance":
        reading.text = (
            f"detectable, within tolerance ({read_mm:.4f} mm <= {tolerance_mm:g} mm): "
            + reading.text
        )
    return {
        "comparison": kind,
        "robot_id": b.robot_id,
        "from_robot_id": a.robot_id,
        "from_recording": a.name,
        "to_recording": b.name,
        "stamp_ns": b.stamp_ns,
        "chi2": diff.T,
        "dof": diff.dof,
        "f_dof": diff.f_dof if np.isfinite(diff.f_dof) else None,
        "p_value": diff.p,
        "alpha": alpha,
        "changed": diff.changed(alpha),
        "kind": reading.kind,
        "cause": reading.cause,
        "columns": list(reading.columns),
        "size": list(reading.beta),
        "size_std": list(reading.beta_std),
        "residual_chi2": reading.residual,
        "residual_dof": reading.residual_dof,
        "groups": list(reading.groups),
        "alternatives": list(reading.alternatives),
        "text": reading.text,
        "read_drift_mm": read_mm,
        "significance": sig,
    }


def run_audit(
    items: list[AuditItem],
    *,
    tolerance_mm: float = TOLERANCE_MM,
    alpha: float = ALPHA,
    models: tuple[str, ...] = MODELS,
    workers: int = 1,
) -> AuditResult:
    """Audit run folders' contents (see the module docstring).

    ``workers``: processes for the per-recording fits and the models x recordings
    matrix (:func:`pipeline.stages.parallel_map.parallel_map`, 0 = the free cores).
    """
    from pipeline.stages.parallel_map import parallel_map

    hist = histories(items)
    flat = [it for runs in hist.values() for it in runs]
    est = dict(zip([it.name for it in flat], parallel_map(fit_item, flat, workers), strict=True))
    rec_rows, ch_rows, lines = [], [], []
    for rid, runs in hist.items():
        lines.append(f"robot {rid}: {len(runs)} recordings")
        for i, it in enumerate(runs):
            row: dict[str, Any] = {
                "robot_id": rid,
                "model": it.model,
                "recording": it.name,
                "stamp_ns": it.stamp_ns,
                "index": i,
                "n_touchups": int(len(est[it.name].q)),
                "previous": runs[i - 1].name if i else "",
                "fresh_mm": np.nan,
                "validated_mm": np.nan,
                "drift_mm": np.nan,
                "drift_raw_mm": np.nan,
                "tolerance_mm": tolerance_mm,
                "passed": True,
                "verdict": "first recording: nothing to validate against",
            }
            if i:
                c = _change_row(
                    "history",
                    runs[i - 1],
                    it,
                    est[runs[i - 1].name],
                    est[it.name],
                    alpha,
                    tolerance_mm,
                )
                v = validate_previous(
                    est[runs[i - 1].name], est[it.name], it, tolerance_mm, c["read_drift_mm"]
                )
                row.update(
                    fresh_mm=v["fresh_mm"], validated_mm=v["validated_mm"],
                    drift_mm=v["drift_mm"], drift_raw_mm=v["drift_raw_mm"], passed=v["passed"],
                    verdict=v["line"],
                )  # fmt: skip
                ch_rows.append(c)
                lines.append(f"  {it.name}: {v['line']}; {c['text']}")
            rec_rows.append(row)
    by_model: dict[str, list[AuditItem]] = {}
    for runs in hist.values():
        by_model.setdefault(runs[0].model, []).append(runs[0])
    for firsts in by_model.values():
        for a, b in zip(firsts, firsts[1:], strict=False):
            c = _change_row("robots", a, b, est[a.name], est[b.name], alpha, tolerance_mm)
            ch_rows.append(c)
            lines.append(f"robots {a.robot_id} vs {b.robot_id}: {c['text']}")
    matrix = model_matrix(flat, models, workers)
    rank = ranking(matrix)
    lines.append(
        "error models by held-out error across the fleet: "
        + ", ".join(
            f"{r.model} (median rank {r.median_rank:g}, RMS {r.rms_heldout_mm:.4f} mm)"
            for r in rank.itertuples()
        )
        + _tied_text(rank)
    )
    return AuditResult(
        pd.DataFrame(rec_rows), pd.DataFrame(ch_rows, columns=CHANGE_COLUMNS), matrix, rank,
        lines, est,
    )  # fmt: skip


def _f_text(f: float) -> str:
    """'' or ", variance factors on 47 dof" (the F test of (C3) in pipeline.audit.change)."""
    return f", variance factors on {f:.0f} dof" if np.isfinite(f) else ""


def _tied_text(rank: pd.DataFrame) -> str:
    """'' or "; not told apart by held-out error: poe, full, mdh" (the models sharing the
    best median rank: the runs' paired tests tied them, :mod:`pipeline.audit.fleet`)."""
    if rank.empty:
        return ""
    best = rank[rank["median_rank"] == rank["median_rank"].iloc[0]]["model"].tolist()
    return "; not told apart by held-out error: " + ", ".join(best) if len(best) > 1 else ""


CHANGE_COLUMNS = [
    "comparison", "robot_id", "from_robot_id", "from_recording", "to_recording", "stamp_ns",
    "chi2", "dof", "f_dof", "p_value", "alpha", "changed", "kind", "cause", "columns", "size",
    "size_std", "residual_chi2", "residual_dof", "groups", "alternatives", "text", "read_drift_mm",
    "significance",
]  # fmt: skip
