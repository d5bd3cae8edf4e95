"""Adding a stage touches the catalog, the stage and (for a Parquet file) its schema only.

As ``tests/test_model_contract.py`` does for an error model, a throw-away stage
is declared here, and only here: its function and options dataclass below, one
:func:`pipeline.run.catalog.register` call for it and its file. ``vtcal identify``
then plans it (after choose), builds its options (``runner.build_configs``),
keys its code (``code_key``), reads its inputs, runs it and writes its file, and
``--set tally.OPTION=VALUE`` reaches it; nothing else of the package is edited
(issue 37). A JSON file needs no schema; a Parquet one would add
``schemas/NAME.json``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_identify import _case

from pipeline.cli import main
from pipeline.commands._common import split_stage_options
from pipeline.io import run_folder
from pipeline.io.run_folder import Artefact
from pipeline.run import catalog, code_key
from pipeline.run.catalog import Stage
from pipeline.run.lazy import Ref

NAME = "tally"


@dataclass
class TallyConfig:
    """The throw-away stage's one option."""

    scale: float = 1.0


def tally(data: Any, config: TallyConfig, context: Any) -> dict[str, Any]:
    """tally.json: the inliers counted and the shipped model named (from identify.json)."""
    inliers = data["inliers"]
    used = int(inliers["inlier"].sum()) if "inlier" in inliers else len(inliers)
    return {"tally": {"inliers": used * config.scale, "best": data["identify"]["best_model"]}}


@pytest.fixture
def throwaway() -> Iterator[str]:
    catalog.register(
        Stage(
            NAME,
            tally,
            ("inliers", "identify"),
            (NAME,),
            Ref(__name__, "TallyConfig"),
            (tally,),  # the function itself: code_key takes its module from tally.__module__
        ),
        Artefact(NAME, "tally.json", NAME),
    )
    try:
        yield NAME
    finally:
        catalog.unregister(NAME)


def test_a_stage_declared_in_the_catalog_runs(throwaway: str, tmp_path: Path) -> None:
    assert catalog.STAGE_NAMES[-1] == throwaway and throwaway in catalog.option_groups()
    assert split_stage_options({"tally.scale": "2"})[1] == {throwaway: {"scale": 2}}
    assert len(code_key.stage_code_digest(throwaway)) == 16
    urdf, _, _, table, targets = _case(seed=5, per_target=6, noise_pin=10e-6)
    csv, urdf_path, out = tmp_path / "t.csv", tmp_path / "r.urdf", tmp_path / "out"
    table.to_csv(csv, index=False)
    urdf_path.write_text(urdf)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    try:
        main(["identify", str(csv), "--urdf", str(urdf_path), "--out", str(out),
              "--base-link", "base_link", "--flange-link", "flange", "--model", "offsets",
              "--distance", f"0:2={d02:.9f}", "--no-report", "--no-crossval"])  # fmt: skip
    except SystemExit as exc:
        assert exc.code in (0, None)
    got = json.loads((out / "tally.json").read_text())
    summary = json.loads((out / "identify.json").read_text())
    assert got == {"inliers": float(len(table)), "best": summary["best_model"]}


def test_unregister_leaves_the_pipeline_as_declared(throwaway: str) -> None:
    catalog.unregister(throwaway)
    assert throwaway not in catalog.STAGE and throwaway not in run_folder.BY_KEY
    assert catalog.STAGE_NAMES[-1] == "report" and "tally.json" not in run_folder.RUN_FILES.values()
    with pytest.raises(ValueError):  # a name taken is refused
        catalog.register(Stage("report", tally, (), (), None))
    catalog.register(Stage(NAME, tally, (), (NAME,), None), Artefact(NAME, "tally.json", NAME))
