"""Provenance block of calibrated.urdf: what it says, that it is deterministic, that readers load it.

The block (pipeline/export/provenance.py) must name the shipped model with its own
held-out and predicted figures from identify.json, the source's hash as the
run ledger computes it, the scale status and a date that is the source's, so
that two runs of the same input give byte-identical files in any folder.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from pipeline.accuracy.verdict import verdict
from pipeline.cli import main
from pipeline.export.provenance import (
    Source,
    provenance_lines,
    read_provenance,
    recorded_utc,
    stamp_urdf,
)
from pipeline.io.fileio import file_hash


def test_provenance_block_in_calibrated_urdf(lrmate_run: Path) -> None:
    yourdfpy = pytest.importorskip("yourdfpy")
    text = (lrmate_run / "calibrated.urdf").read_text()
    summary = json.loads((lrmate_run / "identify.json").read_text())
    prov = read_provenance(text)
    model = summary["best_model"]
    assert prov["shipped model"].startswith(model)
    held = summary["crossval"]["models"][model]["kfold_rms_mm"]
    v = verdict(summary)
    assert v is not None
    assert prov["validated accuracy"].startswith(f"{v['validated_mm']:.4f} mm RMS held-out")
    assert f"{held:.4f} mm each" in prov["validated accuracy"]
    assert f"{summary['predicted_shape_rms_mm']:.4f} mm RMS shape" in prov["predicted accuracy"]
    assert prov["length scale"].startswith("identified from 1 known distance")
    assert file_hash(lrmate_run.parent / "table.csv") in prov["source"]
    assert prov["vtcal version"] and len(prov["run id"].split()[0]) == 16
    assert prov["date"].startswith("unknown")  # a CSV table carries no stamps
    robot = yourdfpy.URDF.load(io.StringIO(text), build_scene_graph=True, load_meshes=False)
    assert robot.robot.name == "lrmate200id_like_calibrated"
    assert "nominal" not in robot.robot.name


def test_provenance_is_deterministic_and_idempotent(lrmate_run: Path, tmp_path: Path) -> None:
    again = tmp_path / "again" / "nested"
    d = json.loads((lrmate_run / "identify.json").read_text())["distances"][0]
    try:
        main(["identify", str(lrmate_run.parent / "table.csv"), "--urdf",
              str(lrmate_run.parent / "nominal.urdf"), "--out", str(again),
              "--distance", f"{d['a']}:{d['b']}={d['metres']!r}", "--no-report"])  # fmt: skip
    except SystemExit as exc:
        assert not exc.code
    a = (lrmate_run / "calibrated.urdf").read_bytes()
    assert (again / "calibrated.urdf").read_bytes() == a  # other folder, same bytes
    text = a.decode()
    src = Source("recording", "x--y.mcap", "0" * 16, "1" * 16, "2026-09-21 08:00 UTC")
    lines = provenance_lines(json.loads((lrmate_run / "identify.json").read_text()), src, "9")
    once = stamp_urdf(text, lines)
    assert stamp_urdf(once, lines) == once  # replaced, not stacked
    assert once.count("vtcal provenance") == 1 and "x- -y.mcap" in once
    assert "2026-09-21 08:00 UTC" in once


def test_provenance_without_crossval_says_so(tmp_path: Path, lrmate_run: Path) -> None:
    out = tmp_path / "nocv"
    try:
        main(["identify", str(lrmate_run.parent / "table.csv"), "--urdf",
              str(lrmate_run.parent / "nominal.urdf"), "--out", str(out), "--model", "full",
              "--no-crossval", "--no-report"])  # fmt: skip
    except SystemExit as exc:
        assert not exc.code
    prov = read_provenance((out / "calibrated.urdf").read_text())
    assert prov["validated accuracy"] == "not cross-validated"
    assert prov["length scale"].startswith("held at the nominal")


def test_date_is_the_earliest_stamp_in_utc() -> None:
    # 1700000000 s after the epoch is 2023-11-14 22:13:20 UTC; 0 and None are "no stamp"
    assert recorded_utc([None, 0, 1_700_000_100_000_000_000, 1_700_000_000_000_000_000]) == (
        "2023-11-14 22:13 UTC"
    )
    assert recorded_utc([0, None]) is None
