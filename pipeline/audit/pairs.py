"""One comparison of the audit: two calibrations tested for a change, the change read.

:func:`compare_pair` is what the audit's engine runs per pair (:mod:`pipeline.audit.work`)
and what its cache keys by code (:mod:`pipeline.audit.cache`): the row of
``audit_changes`` (``schemas/audit_changes.json``) and, for two recordings of one robot,
the previous calibration validated on the later one.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.audit.attribute import Reading, attribute
from pipeline.audit.change import compare_estimates
from pipeline.audit.drift import read_drift_m, validate_previous
from pipeline.audit.fit import Estimate
from pipeline.audit.identity import AuditItem, with_table


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


def compare_pair(
    kind: str,
    a: AuditItem,
    b: AuditItem,
    ea: Estimate,
    eb: Estimate,
    alpha: float,
    tolerance_mm: float,
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """A comparison's row of ``audit_changes`` and, for two recordings of one robot
    (``kind`` ``history``), the previous calibration validated on the later one
    (:func:`pipeline.audit.drift.validate_previous`; None for ``robots``)."""
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
    c = {
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
    if kind != "history":
        return c, None
    return c, validate_previous(ea, eb, with_table(b), tolerance_mm, read_mm)


def _f_text(f: float) -> str:
    """'' or ", variance factors on 47 dof" (the F test of (C3) in pipeline.audit.change)."""
    return f", variance factors on {f:.0f} dof" if np.isfinite(f) else ""


CHANGE_COLUMNS = [
    "comparison", "robot_id", "from_robot_id", "from_recording", "to_recording", "stamp_ns",
    "chi2", "dof", "f_dof", "p_value", "alpha", "changed", "kind", "cause", "columns", "size",
    "size_std", "residual_chi2", "residual_dof", "groups", "alternatives", "text", "read_drift_mm",
    "significance",
]  # fmt: skip
