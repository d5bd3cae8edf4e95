"""``batch.json``: the summary and comparison files of a batch, vouched for.

A batch run again with nothing changed finds there the fingerprint of the batch
that wrote ``summary.parquet`` (and the comparison), and their hashes: when both
still hold, the files are left as they are and no pandas is loaded.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.batch.manifest import BatchItem
from pipeline.batch.outcome import RecordingOutcome
from pipeline.io.run_folder import RUN_FILES

if TYPE_CHECKING:
    from pipeline.run.orchestrator import RunConfig

#: file in the batch folder recording the fingerprint of the batch that wrote the
#: summary and comparison files, their hashes and the comparison's printed lines
BATCH_RECORD = "batch.json"


def batch_fingerprint(
    out_dir: Path,
    items: Sequence[BatchItem],
    outcomes: Sequence[RecordingOutcome],
    config: RunConfig | None,
    until: str | None,
    compare: bool,
) -> dict[str, Any] | None:
    """What the summary and comparison depend on: the items, options, ``until`` and
    every run's ledger entry (recording, options, code, artefact hashes).

    None when a recording did not finish or its run folder has no ledger entry
    (such a batch is never taken as unchanged).
    """
    from pipeline.io.fileio import config_hash
    from pipeline.run import ledger as run_ledger
    from pipeline.run.orchestrator import RunConfig

    if any(o.status != "ok" for o in outcomes):
        return None
    runs = []
    for it in items:
        try:
            led = json.loads((out_dir / it.name / RUN_FILES["run"]).read_text()).get(run_ledger.KEY)
        except (OSError, ValueError, AttributeError):
            return None
        if not isinstance(led, dict):
            return None
        runs.append(config_hash(led))
    return {
        "out": str(out_dir),
        "items": [[it.name, str(it.recording), it.robot, it.notes] for it in items],
        "config": run_ledger.config_json(config or RunConfig()),
        "until": until,
        "compare": compare,
        "runs": runs,
    }


def reusable_record(out_dir: Path, fp: dict[str, Any]) -> dict[str, Any] | None:
    """``batch.json`` when it records ``fp`` and every file it lists is intact, else None."""
    from pipeline.io.fileio import file_hash

    try:
        rec = json.loads((out_dir / BATCH_RECORD).read_text())
        if not isinstance(rec, dict) or rec.get("fingerprint") != fp:
            return None
        files = rec["files"]
        if "summary.parquet" not in files:
            return None
        for name, want in files.items():
            if Path(name).name != name or file_hash(out_dir / name) != want:
                return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    return rec


def write_record(
    out_dir: Path, fp: dict[str, Any], written: Sequence[Path], note: str, lines: Sequence[str]
) -> None:
    """Write ``batch.json`` (atomically, after the files it vouches for)."""
    from pipeline.io.fileio import atomic_write_bytes, file_hash

    rec = {
        "fingerprint": fp,
        "files": {p.name: file_hash(p) for p in written},
        "compare_note": note,
        "compare_lines": list(lines),
    }
    blob = json.dumps(rec, indent=1, sort_keys=True) + "\n"
    atomic_write_bytes(out_dir / BATCH_RECORD, blob.encode())
