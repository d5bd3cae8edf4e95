"""The audit as a Rerun recording (``audit.rrd``): each robot's history on a date timeline.

Per robot ``R`` (entity paths under ``audit/R``), at each recording's first stamp
on the ``date`` timeline: ``drift_mm`` (the drift of the change read),
``drift_raw_mm`` (the two calibrations' difference with their noise),
``validated_mm`` and ``fresh_mm`` (consistencies) as scalars, and each
comparison's reading as a text log entry (``audit/R/changes``) at the later
recording's stamp; for a cause read, its size per column (mm, deg or ppm) under
``audit/R/change/COLUMN``. Written to a temporary sibling, then moved into place.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.audit.attribute import display_unit
from pipeline.audit.audit import AuditResult
from pipeline.io.artefacts import atomic_write_bytes

APP_ID = "vtcal_audit"
SCALARS = ("drift_mm", "drift_raw_mm", "validated_mm", "fresh_mm")


def write_rrd(res: AuditResult, out: Path) -> Path:
    """Write ``out`` (an ``.rrd`` file) for the audit ``res``."""
    import rerun as rr

    out = Path(out)
    tmp = out.with_name(f".{out.name}.partial")
    rec = rr.RecordingStream(APP_ID, recording_id="vtcal-audit", send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(tmp))
    try:
        try:
            for row in res.recordings.to_dict("records"):
                rec.set_time("date", timestamp=np.datetime64(int(row["stamp_ns"]), "ns"))
                for k in SCALARS:
                    v = float(row[k])
                    if math.isfinite(v):
                        rec.log(f"audit/{row['robot_id']}/{k}", rr.Scalars(v))
            hist = res.changes[res.changes["comparison"] == "history"]
            for c in hist.to_dict("records"):
                rec.set_time("date", timestamp=np.datetime64(int(c["stamp_ns"]), "ns"))
                level = "INFO" if not c["changed"] else "WARN"
                rec.log(f"audit/{c['robot_id']}/changes", rr.TextLog(c["text"], level=level))
                for col, v in zip(c["columns"], c["size"], strict=True):
                    f, _unit = display_unit(col)
                    rec.log(f"audit/{c['robot_id']}/change/{col}", rr.Scalars(v * f))
        finally:
            rec.disconnect()
        atomic_write_bytes(out, tmp.read_bytes())
    finally:
        tmp.unlink(missing_ok=True)
    return out
