"""The run folder's catalogue: every file a run writes, declared once.

The names follow ``../shared/spec/outputs.md``. The orchestrator writes these
files; the report, ``vtcal validate``, ``vtcal compare`` and the batch read them.
Kept apart from the orchestrator so that readers need not import the runner
(which imports the report: an import cycle otherwise).
"""

from __future__ import annotations

from pathlib import Path

#: artefact name -> file name inside a run folder (``../shared/spec/outputs.md``)
RUN_FILES = {
    "recording": "recording.json",
    "frames": "frames.parquet",
    "detections": "detections.parquet",
    "touchups": "touchups.parquet",
    "inliers": "inliers.parquet",
    "parameters": "parameters.parquet",
    "residuals": "residuals.parquet",
    "targets": "targets.parquet",
    "calibrated_urdf": "calibrated.urdf",
    "identify": "identify.json",
    "crossval": "crossval.parquet",
    "report": "report.html",
    "rrd": "run.rrd",
    "run": "run.json",
}


def run_paths(out: Path) -> dict[str, Path]:
    """The files a run folder holds, as paths under ``out``."""
    return {k: out / v for k, v in RUN_FILES.items()}
