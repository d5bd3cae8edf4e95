"""`vtcal batch` says what `vtcal run` says: the validated figure and the verdict (issue 35).

A calibration that did not improve on the nominal robot was printed ``ok ... residual RMS
0.2105 mm`` (the training residual) while the same recording alone said "NOT improved".
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from pipeline.accuracy.verdict import verdict
from pipeline.batch.run import RecordingOutcome, take_result
from pipeline.batch.summary import summary_table
from pipeline.commands.batch import _line, print_summary, summary_console


def _summary(kfold: float, nominal: float) -> dict:
    return {
        "best_model": "full",
        "model": "full",
        "rms_mm": 0.2105,
        "n_used": 18,
        "predicted_shape_rms_mm": 0.3,
        "solver": {"initial_rms_mm": nominal},
        "crossval": {"models": {"full": {"kfold_rms_mm": kfold, "kfold_n": 18}}},
        "headline": ["identify [full]: ..."],
    }


def _outcome(tmp_path: Path, name: str, kfold: float, nominal: float, tol: str | None = None):
    run = tmp_path / name
    run.mkdir()
    meta = {"tolerance_mm": tol} if tol else {}
    (run / "recording.json").write_text(json.dumps({"metadata": meta}))
    rec = RecordingOutcome(name=name, recording=f"{name}.mcap", run_dir=str(run))
    stage = SimpleNamespace(stage="identify", status="ran", seconds=1.0)
    take_result(rec, SimpleNamespace(stages=[stage], summary=_summary(kfold, nominal)))
    return rec


def test_a_run_that_did_not_improve_is_not_ok(tmp_path: Path) -> None:
    rec = _outcome(tmp_path, "small_s1", kfold=0.95, nominal=0.8310)
    line = _line(rec)
    assert not line.strip().startswith("ok"), line
    assert "not improved" in line and "NOT improved" in line
    assert "0.9500 mm RMS held-out" in line  # the validated figure, not the training one
    assert line.endswith(verdict(_summary(0.95, 0.8310))["line"])  # one wording, the run's
    assert rec.state == "not improved" and rec.exit_code == 0  # as `vtcal run`: exit 0


def test_a_tolerance_from_the_recording_fails_as_the_run_would(tmp_path: Path) -> None:
    rec = _outcome(tmp_path, "tight", kfold=0.06, nominal=1.2, tol="0.01")
    assert rec.state == "FAIL" and rec.exit_code == 3
    assert "| FAIL (0.0600 mm > 0.01 mm)" in _line(rec)
    good = _outcome(tmp_path, "good", kfold=0.06, nominal=1.2)
    assert good.state == "ok" and _line(good).strip().startswith("ok")


def test_the_table_headlines_the_validated_figure(tmp_path: Path) -> None:
    outs = [
        _outcome(tmp_path, "bad", kfold=0.95, nominal=0.8310),
        _outcome(tmp_path, "good", kfold=0.06, nominal=1.2),
    ]
    result = SimpleNamespace(
        out_dir=tmp_path,
        outcomes=outs,
        failed=[],
        compare_lines=[],
        compare_note="-",
        n_ok=2,
        seconds=1.0,
        summary_path=tmp_path / "summary.parquet",
    )
    buf = io.StringIO()
    print_summary(summary_console(buf), result)  # type: ignore[arg-type]
    text = buf.getvalue()
    header = next(line for line in text.splitlines() if "validated mm" in line)
    assert header.index("validated mm") < header.index("training mm")
    bad = next(line for line in text.splitlines() if line.lstrip("│ ").startswith("bad"))
    assert "not improved" in bad and "0.9500" in bad and "0.8310" in bad
    assert "1 of 2 recording(s) ok, 1 not improved in" in text
    df = summary_table(outs)
    assert list(df["verdict"]) == ["not improved", "improved"]
    assert df["validated_mm"].tolist() == pytest.approx([0.95, 0.06])
    assert df["nominal_mm"].tolist() == pytest.approx([0.8310, 1.2])
