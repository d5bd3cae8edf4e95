"""Determinism: the same recording and options give the same artefacts, wherever the run folder.

Two runs of the sample recording into two different folders must give
byte-identical Parquet files (so equal data columns, equal schemas and equal
``vtcal.*`` metadata: input hashes, configuration hash, version). Artefact
metadata records hashes of inputs, never paths or times, and Parquet is
written without a creation timestamp, which is what makes this hold. The JSON
side files may differ only in wall-clock ``seconds`` fields.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from pipeline.cli import main

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
PARQUET = [
    "frames.parquet",
    "detections.parquet",
    "touchups.parquet",
    "inliers.parquet",
    "parameters.parquet",
    "residuals.parquet",
    "targets.parquet",
    "crossval.parquet",
]


def _run(out: Path) -> None:
    try:
        main(["run", str(SAMPLE), "--out", str(out), "--until", "crossval", "-q"])
    except SystemExit as exc:  # click's standalone exit on success is 0
        assert not exc.code, exc.code


def _no_times(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _no_times(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_no_times(v) for v in obj]
    return obj


def test_two_runs_in_different_folders_give_identical_artefacts(tmp_path: Path) -> None:
    a, b = tmp_path / "first", tmp_path / "second" / "nested"
    _run(a)
    _run(b)
    for name in PARQUET:
        ta, tb = pq.read_table(a / name), pq.read_table(b / name)
        assert ta.schema.equals(tb.schema, check_metadata=True), name
        assert ta.equals(tb), name
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    for name in ("calibrated.urdf", "recording.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    ja = json.loads((a / "identify.json").read_text())
    jb = json.loads((b / "identify.json").read_text())
    assert _no_times(ja) == _no_times(jb)
