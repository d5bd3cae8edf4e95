"""Which robots need attention first: the order of the audit page's fleet table.

One row per robot (:func:`fleet_status`), each in one of four classes, in this order:

1. ``failed``: its latest validation did not pass (on its latest recording the previous
   calibration's drift or validated consistency is beyond the tolerance);
2. ``changed``: its latest comparison found a change that matters (significance
   ``beyond_tolerance``: a drift beyond the tolerance, a change without a drift figure,
   or a recording read as a different robot, :func:`pipeline.audit.audit.significance`);
3. ``overdue``: no recording for longer than the interval (``interval_days``), counted
   to ``now_ns``, the audit's time; without an interval nothing is overdue;
4. ``ok``: the rest. A change within the tolerance is said in the row, not ranked up.

Within a class, worst first: the larger of drift and validated consistency (failed), the
larger drift the change read, one without a figure first (changed), the older last
recording (overdue), the larger drift (ok); then the larger drift, then the robot's name.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pandas as pd

#: the classes, most urgent first
STATUSES = ("failed", "changed", "overdue", "ok")
DAY_NS = 86_400 * 10**9
#: a change read without one cause, in the fleet table's words
WORDS = {"different_robot": "a different robot", "several": "several changes at once"}

COLUMNS = [
    "robot_id", "model", "status", "n_recordings", "last_recording", "last_stamp_ns",
    "age_days", "overdue", "drift_mm", "validated_mm", "tolerance_mm", "passed", "changed",
    "significance", "kind", "cause", "read_drift_mm", "severity",
]  # fmt: skip


def _finite(x: Any) -> float:
    try:
        f = float(x)
    except (TypeError, ValueError):
        return math.nan
    return f if math.isfinite(f) else math.nan


Rows = list[dict[Any, Any]]


def rows_of(df: pd.DataFrame | Rows) -> Rows:
    """A table's rows as dicts: ``df.to_dict("records")`` without its per-column indexing
    (a few ms per call on a few-row table: seconds over hundreds of robots); a list is
    taken as it is."""
    if not isinstance(df, pd.DataFrame):
        return df
    cols = [df[c].to_numpy(dtype=object).tolist() for c in df.columns]
    return [dict(zip(df.columns, vals, strict=True)) for vals in zip(*cols, strict=True)]


def _significance(c: dict[Any, Any] | None) -> str:
    if c is None:
        return "none"
    if "significance" in c and isinstance(c["significance"], str):
        return c["significance"]
    return "beyond_tolerance" if bool(c.get("changed")) else "none"  # tables without it


def _severity(status: str, row: dict[Any, Any]) -> float:
    """How bad within its class (larger first); an unknown figure counts as the worst."""
    if status == "failed":
        worst = np.nanmax([row["drift_mm"], row["validated_mm"], -math.inf])
        return math.inf if worst == -math.inf else float(worst)
    if status == "changed":
        return math.inf if math.isnan(row["read_drift_mm"]) else row["read_drift_mm"]
    if status == "overdue":
        return float(row["age_days"])
    return -1.0 if math.isnan(row["drift_mm"]) else row["drift_mm"]


def fleet_status_rows(
    recordings: pd.DataFrame | Rows,
    changes: pd.DataFrame | Rows,
    *,
    now_ns: int | None = None,
    interval_days: float | None = None,
) -> Rows:
    """:func:`fleet_status` as a list of row dicts, in the order of attention."""
    now = time.time_ns() if now_ns is None else int(now_ns)
    latest = {
        (str(c["robot_id"]), str(c["to_recording"])): c
        for c in rows_of(changes)
        if c["comparison"] == "history"
    }
    last: dict[Any, dict[Any, Any]] = {}
    count: dict[Any, int] = {}
    for r in rows_of(recordings):
        rid = r["robot_id"]
        count[rid] = count.get(rid, 0) + 1
        if rid not in last or (r["index"], r["stamp_ns"]) >= (
            last[rid]["index"],
            last[rid]["stamp_ns"],
        ):
            last[rid] = r
    rows = [_status(rid, last[rid], count[rid], latest, now, interval_days) for rid in last]
    rows.sort(key=_order)
    return rows


def _order(row: dict[Any, Any]) -> tuple[int, float, float, str]:
    """The sort key: class, worse first, then the larger drift, then the name."""
    drift = -1.0 if math.isnan(row["drift_mm"]) else row["drift_mm"]
    return STATUSES.index(row["status"]), -row["severity"], -drift, str(row["robot_id"])


def _status(
    rid: Any,
    last: dict[Any, Any],
    n: int,
    latest: dict[tuple[str, str], dict[Any, Any]],
    now: int,
    interval_days: float | None,
) -> dict[Any, Any]:
    """One robot's row of :func:`fleet_status` from its last recording and its comparison."""
    c = latest.get((str(rid), str(last["recording"])))
    sig = _significance(c)
    kind = str(c.get("kind", "none")) if c is not None else "none"
    age = (now - int(last["stamp_ns"])) / DAY_NS
    row = {
        "robot_id": rid,
        "model": last.get("model", ""),
        "n_recordings": n,
        "last_recording": last["recording"],
        "last_stamp_ns": int(last["stamp_ns"]),
        "age_days": age,
        "overdue": interval_days is not None and age > interval_days,
        "drift_mm": _finite(last.get("drift_mm")),
        "validated_mm": _finite(last.get("validated_mm")),
        "tolerance_mm": _finite(last.get("tolerance_mm")),
        "passed": bool(last.get("passed", True)),
        "changed": bool(c is not None and c.get("changed")),
        "significance": sig,
        "kind": kind,
        "cause": str(c.get("cause") or "") if c is not None else "",
        "read_drift_mm": _finite(c.get("read_drift_mm")) if c is not None else math.nan,
    }
    if int(last.get("index", 0)) > 0 and not row["passed"]:
        row["status"] = "failed"
    elif sig == "beyond_tolerance" or kind == "different_robot":
        row["status"] = "changed"
    else:
        row["status"] = "overdue" if row["overdue"] else "ok"
    row["severity"] = _severity(row["status"], row)
    return row


def fleet_status(
    recordings: pd.DataFrame,
    changes: pd.DataFrame,
    *,
    now_ns: int | None = None,
    interval_days: float | None = None,
) -> pd.DataFrame:
    """One row per robot in the order of attention (see the module docstring).

    Parameters
    ----------
    recordings, changes : the audit's tables (:class:`pipeline.audit.audit.AuditResult`)
    now_ns : the audit's time (ns since the epoch); the clock's when None
    interval_days : a robot with no recording for longer than this is overdue; None: never

    Returns
    -------
    DataFrame of :data:`COLUMNS`: ``status`` one of :data:`STATUSES`, ``age_days`` the
    days from the last recording to ``now_ns``, the latest recording's figures
    (``drift_mm``, ``validated_mm``, ``passed``) and its comparison's (``changed``,
    ``significance``, ``kind``, ``cause``, ``read_drift_mm``).
    """
    rows = fleet_status_rows(recordings, changes, now_ns=now_ns, interval_days=interval_days)
    return pd.DataFrame(rows, columns=COLUMNS)


def reading(row: dict[Any, Any]) -> str:
    """The row's why, in a few words: what failed and the change its latest comparison
    read (``drift beyond 0.1 mm; joint_3 zero offset``, ``camera / pin remounted, within
    tolerance (0.0230 mm)``); empty when there is nothing to say."""
    from pipeline.io.numfmt import fmt, short

    parts = []
    if row["status"] == "failed":
        drift_over = row["drift_mm"] > row["tolerance_mm"]  # else the validated consistency
        what = "drift" if drift_over else "validated consistency"
        parts.append(f"{what} beyond {short(row['tolerance_mm'])} mm")
    if row["changed"]:
        what = row["cause"] or WORDS.get(row["kind"], str(row["kind"]).replace("_", " "))
        if row["significance"] == "within_tolerance":
            what += f", within tolerance ({fmt(row['read_drift_mm'], 4)} mm)"
        parts.append(what)
    return "; ".join(parts)
