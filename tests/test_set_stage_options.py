"""``--set STAGE.OPTION=VALUE`` reaches the stage's config; other keys stay metadata overrides."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from pipeline.commands._common import split_stage_options
from pipeline.errors import BadInput

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"


def test_stage_options_are_split_and_typed():
    meta, stages = split_stage_options(
        {
            "polarity": "dark_on_light",
            "identify.target_shape": "none",
            "detect.clip_correction": "false",
            "identify.shape_alpha": "1e-5",
            "outliers.max_correctable_size_px": "2",
            "unknown.thing": "x",
        }
    )
    assert meta == {"polarity": "dark_on_light", "unknown.thing": "x"}
    assert stages == {
        "identify": {"target_shape": "none", "shape_alpha": 1e-5},
        "detect": {"clip_correction": False},
        "outliers": {"max_correctable_size_px": 2},
    }


def test_run_takes_a_stage_option_and_refuses_an_unknown_one(tmp_path: Path):
    out = tmp_path / "run"
    res = CliRunner().invoke(
        cli,
        ["run", str(SAMPLE), "--out", str(out), "-q", "--until", "identify",
         "--set", "identify.target_shape=fit", "--no-report"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "identify.json").read_text())
    # 'fit' keeps the print shape whenever it can be fitted (the sample has 6 touch-ups per
    # target at most, so it says why it was not)
    assert meta["print_shape"] is not None
    res = CliRunner().invoke(
        cli,
        ["run", str(SAMPLE), "--out", str(tmp_path / "bad"), "-q", "--until", "identify",
         "--set", "identify.no_such_option=1", "--no-report"],
    )  # fmt: skip
    # BadInput: the CLI's entry point turns it into one line and exit 2
    assert isinstance(res.exception, BadInput), res.output
    assert "no_such_option" in str(res.exception)


@pytest.mark.parametrize("text,value", [("true", True), ("3", 3), ("0.5", 0.5), ("auto", "auto")])
def test_option_values(text, value):
    assert split_stage_options({"identify.x": text})[1]["identify"]["x"] == value
