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

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.audit.change import ALPHA
from pipeline.audit.drift import TOLERANCE_MM
from pipeline.audit.fit import Estimate
from pipeline.audit.fleet import MODELS, matrix_table, ranking
from pipeline.audit.identity import AuditItem, histories
from pipeline.audit.pairs import CHANGE_COLUMNS as CHANGE_COLUMNS
from pipeline.audit.pairs import significance as significance


@dataclass
class AuditResult:
    """The audit's tables and its summary lines."""

    recordings: pd.DataFrame
    changes: pd.DataFrame
    models: pd.DataFrame
    ranking: pd.DataFrame
    lines: list[str] = field(default_factory=list)
    estimates: Mapping[str, Estimate] = field(default_factory=dict, repr=False)
    #: ``{"fits" | "held-out" | "comparisons": (computed, taken from the cache)}``
    counts: dict[str, tuple[int, int]] = field(default_factory=dict)


def run_audit(
    items: list[AuditItem],
    *,
    tolerance_mm: float = TOLERANCE_MM,
    alpha: float = ALPHA,
    models: tuple[str, ...] = MODELS,
    workers: int | None = 1,
    executor: str = "processes",
    scheduler: str | None = None,
    cache_dir: Path | None = None,
) -> AuditResult:
    """Audit run folders' contents (see the module docstring).

    ``executor``, ``workers``, ``scheduler``: where the fits, the models x recordings
    matrix and the comparisons run (:mod:`pipeline.audit.engine`: the batch's
    executors; the process pool with one worker is this process, 0 or None the free
    cores). ``cache_dir``: the audit folder whose ``cache/`` keeps every fit,
    held-out figure and comparison (:mod:`pipeline.audit.cache`): what it holds is
    not computed again. The tables are the same wherever the work ran.
    """
    from pipeline.audit.cache import Cache
    from pipeline.audit.engine import Engine
    from pipeline.audit.work import AuditWork

    hist = histories(items)
    flat = [it for runs in hist.values() for it in runs]
    pairs = [("history", r[i - 1], r[i]) for r in hist.values() for i in range(1, len(r))]
    by_model: dict[str, list[AuditItem]] = {}
    for runs in hist.values():
        by_model.setdefault(runs[0].model, []).append(runs[0])
    for firsts in by_model.values():
        pairs += [("robots", a, b) for a, b in zip(firsts, firsts[1:], strict=False)]
    work = AuditWork(Cache(cache_dir), alpha, tolerance_mm)
    with Engine(executor, workers, scheduler, cache_dir) as engine:
        work.run(hist, models, pairs, engine)
    rec_rows, ch_rows, lines = [], [], []
    for rid, runs in hist.items():
        lines.append(f"robot {rid}: {len(runs)} recordings")
        for i, it in enumerate(runs):
            rec_rows.append(_recording_row(rid, runs, i, work.n_touchups[it.name], tolerance_mm))
            if i:
                c, v = work.comparison(runs[i - 1], it, "history")
                rec_rows[-1].update(
                    fresh_mm=v["fresh_mm"], validated_mm=v["validated_mm"],
                    drift_mm=v["drift_mm"], drift_raw_mm=v["drift_raw_mm"], passed=v["passed"],
                    verdict=v["line"],
                )  # fmt: skip
                ch_rows.append(c)
                lines.append(f"  {it.name}: {v['line']}; {c['text']}")
    for kind, a, b in pairs:
        if kind == "robots":
            c, _ = work.comparison(a, b, kind)
            ch_rows.append(c)
            lines.append(f"robots {a.robot_id} vs {b.robot_id}: {c['text']}")
    matrix = matrix_table(flat, models, work.runs, work.heldout)
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
        lines, work.estimates(), work.counts,
    )  # fmt: skip


def _recording_row(
    rid: str, runs: list[AuditItem], i: int, n_touchups: int, tolerance_mm: float
) -> dict[str, Any]:
    it = runs[i]
    return {
        "robot_id": rid,
        "model": it.model,
        "recording": it.name,
        "stamp_ns": it.stamp_ns,
        "index": i,
        "n_touchups": n_touchups,
        "previous": runs[i - 1].name if i else "",
        "fresh_mm": np.nan,
        "validated_mm": np.nan,
        "drift_mm": np.nan,
        "drift_raw_mm": np.nan,
        "tolerance_mm": tolerance_mm,
        "passed": True,
        "verdict": "first recording: nothing to validate against",
    }


def _tied_text(rank: pd.DataFrame) -> str:
    """'' or "; not told apart by held-out error: poe, full, mdh" (the models sharing the
    best median rank: the runs' paired tests tied them, :mod:`pipeline.audit.fleet`)."""
    if rank.empty:
        return ""
    best = rank[rank["median_rank"] == rank["median_rank"].iloc[0]]["model"].tolist()
    return "; not told apart by held-out error: " + ", ".join(best) if len(best) > 1 else ""
