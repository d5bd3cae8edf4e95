"""Every headline figure is the shipped model's, checked against that model's own artefact rows.

Issue 15: on the shipped sample and on the standard simulated cell, identify.json's
top level, the report, the batch summary and ``vtcal compare`` must agree figure
for figure with the rows the shipped model wrote in parameters.parquet,
residuals.parquet and crossval.parquet (before, they were ``full``'s whatever
model was shipped). Each figure is recomputed here from the Parquet rows, not
read back from the summary.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.verdict import verdict
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.sim.scenario import scenario_from_dict
from pipeline.sim.simulator import write_recording

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"


@pytest.fixture(scope="module", params=["sample", "standard"])
def run_dir(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    work = tmp_path_factory.mktemp(request.param)
    if request.param == "sample":
        rec = SAMPLE
    else:  # the standard LR Mate-like cell, 3 targets x 6 poses to keep it short
        raw = tomllib.loads((REPO / "datasets/scenarios/standard.toml").read_text())
        raw["poses"]["per_target"] = 6
        sc = scenario_from_dict(raw, where="standard", base_dir=str(REPO))
        rec = work / "standard.mcap"
        write_recording(sc, 3, rec)
    out = work / "run"
    run_pipeline(rec, out, RunConfig())
    return out


def _rows(run_dir: Path, name: str, model: str) -> pd.DataFrame:
    df = pd.read_parquet(run_dir / f"{name}.parquet")
    return df[df["model"] == model]


def test_identify_json_is_the_shipped_models_rows(run_dir: Path) -> None:
    s = json.loads((run_dir / "identify.json").read_text())
    best = s["best_model"]
    assert s["model"] == best
    par = _rows(run_dir, "parameters", best)
    kin = par[par["kind"] == "kinematic"]
    assert len(kin) == s["n_params"]
    assert int(kin["identifiable"].sum()) == s["n_identified"]
    pin = par[par["kind"] == "pin"].set_index("name")["value"]
    assert [pin[f"pin.{a}"] for a in "xyz"] == pytest.approx(s["p_flange_pin"], abs=1e-15)
    res = _rows(run_dir, "residuals", best)
    used = res[res["used"]]
    assert len(used) == s["n_used"]
    norms = np.sqrt(used["rx"] ** 2 + used["ry"] ** 2 + used["rz"] ** 2)
    assert s["rms_mm"] == pytest.approx(1e3 * float(np.sqrt(np.mean(norms**2))), rel=1e-9)
    assert s["max_mm"] == pytest.approx(1e3 * float(norms.max()), rel=1e-9)
    cv = _rows(run_dir, "crossval", best)
    kfold = cv[(cv["scheme"] == "kfold") & cv["error_mm"].notna()]
    own_cv = s["crossval"]["models"][best]
    assert own_cv["kfold_rms_mm"] == pytest.approx(
        float(np.sqrt(np.mean(kfold["error_mm"] ** 2))), rel=1e-9
    )
    v = verdict(s)
    # (V2) of pipeline.accuracy.verdict from the shipped rows' own figures
    own = s["rms_mm"] * np.sqrt(3 * s["n_rows"] / s["dof"])
    k = s["crossval"]["k"]
    beyond = np.sqrt(max(own_cv["kfold_rms_mm"] ** 2 - own**2, 0.0) * (k - 1) / k)
    # absolute with a known distance (the scale identified), shape without
    kind = "shape" if s["scale_held"] else "absolute"
    want = max(s[f"predicted_{kind}_rms_mm"], beyond)
    assert v is not None and v["validated_mm"] == pytest.approx(want, rel=1e-12)


def test_the_report_batch_and_compare_show_the_same_figures(run_dir: Path, tmp_path) -> None:
    s = json.loads((run_dir / "identify.json").read_text())
    best = s["best_model"]
    cv = _rows(run_dir, "crossval", best)
    kfold = cv[(cv["scheme"] == "kfold") & cv["error_mm"].notna()]
    held_out = float(np.sqrt(np.mean(kfold["error_mm"] ** 2)))
    html = (run_dir / "report.html").read_text()
    assert f"{held_out:.4f}" in html, "the report's validated figure is the shipped model's"
    assert f"{s['rms_mm']:.4f}" in html, "the training residual is the shipped model's"
    # batch summary figures
    from pipeline.batch.run import FIGURES_FLOAT, FIGURES_INT, RecordingOutcome, take_result

    rec = RecordingOutcome(name="r", recording="r.mcap", run_dir=str(run_dir))
    stage = SimpleNamespace(stage="identify", status="cached", seconds=0.0)
    take_result(rec, SimpleNamespace(stages=[stage], summary=s))
    assert rec.figures["model"] == best
    own = s["models"][best]
    for key in FIGURES_INT + FIGURES_FLOAT:
        if isinstance(own.get(key), (int, float)):
            assert rec.figures[key] == own[key], key
    # vtcal compare of the run with itself: the shipped model's held-out figure, nothing moved
    from pipeline.accuracy.compare import compare_runs

    cmp = compare_runs([run_dir, run_dir])
    shipped = cmp.runs[cmp.runs["shipped"]]
    assert len(shipped) == 2 and set(shipped["model"]) == {best}
    for row in shipped.itertuples():
        assert row.heldout_rms_mm == pytest.approx(held_out, rel=1e-9)
        assert row.train_rms_mm == pytest.approx(s["rms_mm"], rel=1e-12)
        assert row.cond == pytest.approx(s["cond"], rel=1e-12)
        assert row.n_used == s["n_used"]
    assert cmp.moved.empty
