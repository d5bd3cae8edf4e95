"""`vtcal identify` writes what `vtcal run` writes from identification on (spec touchups.md)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from pipeline.cli import main
from pipeline.io.artefacts import read_artefact

REPO = Path(__file__).resolve().parent.parent
TRUTH = REPO / "datasets" / "samples" / "sample_lrmate.mcap.truth.json"


def test_identify_string_targets_crossval_and_report(tmp_path: Path) -> None:
    truth = json.loads(TRUTH.read_text())
    rows = [
        {
            "touchup_id": i,
            "target_id": f"T{tu['label']}",
            **dict(zip(truth["joint_names"], tu["q"], strict=True)),
        }
        for i, tu in enumerate(truth["touchups"])
        if tu["converged"]
    ]
    table = tmp_path / "table.csv"
    pd.DataFrame(rows).to_csv(table, index=False)
    urdf = tmp_path / "nominal.urdf"
    urdf.write_text(truth["nominal_urdf"])
    kd = truth["known_distances"][0]
    a, b = (f"T{x}" for x in kd["labels"])
    out = tmp_path / "out"
    try:
        main(["identify", str(table), "--urdf", str(urdf), "--out", str(out),
              "--distance", f"{a}:{b}={kd['metres']}"])  # fmt: skip
    except SystemExit as exc:
        assert exc.code in (0, None)
    for name in ("calibrated.urdf", "report.html", "run.rrd", "identify.json"):
        assert (out / name).is_file(), name
    cv = read_artefact(out / "crossval.parquet", "crossval")
    assert set(cv["target_id"]) == {0, 1, 2}
    summary = json.loads((out / "identify.json").read_text())
    assert "held-out" in summary["headline"][-1]
    targets = read_artefact(out / "targets.parquet", "targets")
    assert {"T0", "T1", "T2"} <= set(targets["target_label"].astype(str))
