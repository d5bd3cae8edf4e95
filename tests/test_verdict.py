"""The verdict: the shipped model's validated (held-out) error against the nominal robot's.

The headline must not be a training residual, and a run whose validated error is not
clearly below the nominal robot's must not show an improvement.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.accuracy.verdict import IMPROVED_BELOW, verdict
from pipeline.cli import cli
from pipeline.report.html import build_report

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"


def _summary(kfold=0.06, nominal=1.2, fit=0.013, pred=0.05):
    return {
        "best_model": "mdh",
        "model": "mdh",
        "rms_mm": fit,
        "predicted_shape_rms_mm": pred,
        "solver": {"initial_rms_mm": nominal},
        "crossval": {
            "models": {"mdh": {"kfold_rms_mm": kfold, "kfold_max_mm": 0.2, "kfold_n": 18}}
        },  # fmt: skip
    }


def test_the_headline_is_the_held_out_error_not_the_fit():
    v = verdict(_summary())
    assert v["validated_mm"] == 0.06 and "held-out" in v["validated_how"]
    assert v["fit_mm"] == 0.013 and v["improved"] is True
    assert v["ratio"] == pytest.approx(20.0)
    assert "0.0600 mm RMS held-out" in v["line"] and "(training)" in v["line"]


def test_a_held_out_error_above_the_nominal_is_not_an_improvement():
    v = verdict(_summary(kfold=1.5, nominal=1.2))
    assert v["improved"] is False and "NOT improved" in v["line"]
    # "clearly below": just under the nominal is not enough either
    v = verdict(_summary(kfold=IMPROVED_BELOW * 1.2 * 1.01, nominal=1.2))
    assert v["improved"] is False


def test_without_crossval_the_prediction_is_named_as_such():
    s = _summary()
    del s["crossval"]
    v = verdict(s)
    assert v["validated_mm"] == 0.05 and "predicted" in v["validated_how"]
    assert verdict(None) is None


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("verdict") / "run"
    res = CliRunner().invoke(cli, ["run", str(SAMPLE), "--out", str(out), "-q", "--no-report"])
    assert res.exit_code == 0, res.output
    assert "verdict: model" in res.output and "held-out" in res.output
    return out


def test_the_report_headline_is_validated(sample_run):
    text = build_report(sample_run).read_text()
    summary = json.loads((sample_run / "identify.json").read_text())
    kfold = summary["crossval"]["models"][summary["best_model"]]["kfold_rms_mm"]
    assert "RMS, validated" in text and f"{kfold:.4f} mm each" in text
    assert "fit residual (training, not an accuracy)" in text
    assert "improvement" in text and "not improved" not in text


def test_a_run_worse_than_nominal_shows_no_improvement(sample_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    p = run / "identify.json"
    summary = json.loads(p.read_text())
    best = summary["best_model"]
    summary["crossval"]["models"][best]["kfold_rms_mm"] = 50.0  # far beyond the nominal
    p.write_text(json.dumps(summary))
    text = build_report(run).read_text()
    assert "not improved" in text
    assert '<div class="card ratio">' not in text  # no green improvement card


def test_a_tolerance_passes_or_fails_the_validated_error():
    assert verdict(_summary(kfold=0.06), tolerance_mm=0.1)["passed"] is True
    v = verdict(_summary(kfold=0.06), tolerance_mm=0.05)
    assert v["passed"] is False and "FAIL (0.0600 mm > 0.05 mm)" in v["line"]
    # within the tolerance but no better than the nominal robot: FAIL too
    v = verdict(_summary(kfold=0.06, nominal=0.065), tolerance_mm=0.1)
    assert v["passed"] is False and "not improved" in v["line"]
    s = _summary()
    del s["crossval"], s["predicted_shape_rms_mm"]
    assert verdict(s, tolerance_mm=1.0)["passed"] is False  # nothing validated


def test_the_cli_exits_3_on_fail_and_0_on_pass(sample_run):
    from pipeline.errors import CalibrationFailed

    args = ["run", str(SAMPLE), "--out", str(sample_run), "-q", "--no-report"]
    res = CliRunner().invoke(cli, [*args, "--tolerance-mm", "0.001"])
    assert isinstance(res.exception, CalibrationFailed), res.output  # exit 3 via main()
    assert "verdict FAIL" in str(res.exception) and "| FAIL (" in res.output
    res = CliRunner().invoke(cli, [*args, "--tolerance-mm", "1.0"])
    assert res.exit_code == 0 and "| PASS (" in res.output, res.output


def test_the_report_shows_pass_or_fail_from_the_metadata(sample_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    p = run / "recording.json"
    rec = json.loads(p.read_text())
    rec.setdefault("metadata", {})["tolerance_mm"] = "0.001"
    p.write_text(json.dumps(rec))
    text = build_report(run).read_text()
    assert "<b>FAIL</b>" in text and "0.001 mm" in text
    rec["metadata"]["tolerance_mm"] = "1"
    p.write_text(json.dumps(rec))
    assert "<b>PASS</b>" in build_report(run).read_text()


def test_the_report_shows_the_cli_tolerance_and_keeps_it(sample_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    args = ["run", str(SAMPLE), "--out", str(run), "-q"]
    res = CliRunner().invoke(cli, [*args, "--tolerance-mm", "0.001"])
    assert res.exception is not None  # FAIL, exit 3
    text = (run / "report.html").read_text()
    assert "<b>FAIL</b>" in text and "0.001 mm" in text, "the report judges the CLI's tolerance"
    assert json.loads((run / "run.json").read_text())["tolerance_mm"] == 0.001
    # re-rendered later, the report keeps the run's tolerance; --tolerance-mm replaces it
    assert "<b>FAIL</b>" in build_report(run).read_text()
    assert "<b>PASS</b>" in build_report(run, tolerance_mm=1.0).read_text()
    res = CliRunner().invoke(cli, [*args, "--tolerance-mm", "1.0"])
    assert res.exit_code == 0 and "<b>PASS</b>" in (run / "report.html").read_text()


def _banner(text: str) -> str:
    i = text.index('<div class="banner bad"><b>FAIL</b>')
    return text[i : text.index("</div>", i)]


def test_the_fail_banner_names_where_its_tolerance_came_from(sample_run, tmp_path):
    """Issue 35: --tolerance-mm on the command line was called 'the recording's tolerance_mm'."""
    given = build_report(sample_run, tmp_path / "given.html", tolerance_mm=0.001).read_text()
    assert "given on the command line" in _banner(given)
    assert "recording&#39;s" not in _banner(given) and "recording's" not in _banner(given)
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    p = run / "recording.json"
    rec = json.loads(p.read_text())
    rec.setdefault("metadata", {})["tolerance_mm"] = "0.001"
    p.write_text(json.dumps(rec))
    (run / "run.json").write_text(
        json.dumps({**json.loads((run / "run.json").read_text()), "tolerance_mm": None})
    )
    meta = build_report(run).read_text()
    assert "tolerance_mm metadata key" in _banner(meta)


def test_the_report_gives_the_consoles_nominal_figure(sample_run, tmp_path):
    """Issue 35: the FAIL banner said 'nominal robot's 1.1926 mm' where the console said
    1.1929 mm; the report now takes identify.json's figure, as the console does."""
    summary = json.loads((sample_run / "identify.json").read_text())
    console = verdict(summary, 0.001)["line"]
    text = build_report(sample_run, tmp_path / "r.html", tolerance_mm=0.001).read_text()
    assert console.replace("'", "&#39;").replace(">", "&gt;") in _banner(text)
    nominal = summary["solver"]["initial_rms_mm"]
    card = text[text.index('<div class="card before">') : text.index('<div class="card after">')]
    assert f"{nominal:.4f}" in card


def test_a_covariance_predicted_figure_is_not_titled_validated(sample_run, tmp_path):
    """Issue 35: without cross-validation the 'after' card said 'RMS, VALIDATED' above a
    note saying 'predicted from the parameter covariance (not cross-validated)'."""
    run = tmp_path / "run"
    shutil.copytree(sample_run, run)
    p = run / "identify.json"
    summary = json.loads(p.read_text())
    del summary["crossval"]
    summary["solver"]["initial_rms_mm"] = 0.05  # and not improved
    p.write_text(json.dumps(summary))
    text = build_report(run).read_text()
    card = text[text.index('<div class="card after">') :]
    title = card[: card.index("</div>")]
    assert "predicted (not cross-validated)" in title and "validated" not in title.replace(
        "not cross-validated", ""
    )
    assert "not improved" in text
