"""End to end on images formed as real cameras form them (issue 14).

Twins of one simulated cell (same seed: same robot, targets, plan and noise
draws), each calibrated by the whole pipeline and judged against the truth:

* sRGB-encoded images calibrate within 1.5x of the linear twin on the standard
  cell's 36 touch-ups (before vtcal linearised its grey levels, every long axis
  read ~0.4-0.8 px short and the pin sat millimetres off along the view: ~1.2 mm
  here). With 24 touch-ups they do not yet: 0.035 / 0.024 / 0.060 mm against
  0.011 / 0.018 / 0.009 mm on seeds 7 / 8 / 9. The controller's own detector reads the encoded
  image ~0.43 px short, every touch-up is corrected by ~1.3 mm along the view, and
  the image Jacobian's size row is known to ~1 % per target (with an unbiased
  controller the same images give 0.019 / 0.021 mm on seeds 7 / 9);
* uneven light with a controller whose simpler detector it fools (binary blob
  moments at one global threshold, ~1.5 px short and a few tenths of a pixel off
  centre) keeps its touch-ups (before: 17 of 18 rejected as "not converged") and
  calibrates to under 0.1 mm (0.068 mm on seed 7; the same limit as above, with
  ~4.7 mm of along-view correction per touch-up).

* prints 20 um out of round (2 um rough) calibrate to under 0.05 mm, with the print
  shape identified (0.020 / 0.008 / 0.020 mm on seeds 7 / 8 / 9 against the linear
  twins' 0.013 / 0.018 / 0.009 mm; without the print-shape fit the same cell is
  0.13 mm off with 36 touch-ups: the long axis follows the camera's roll).

What limits the first two is written up in ``docs/detection.md`` ("Real cameras: what is
left").
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.artefacts import read_artefact
from pipeline.evaluate import pin_accuracy, workspace_poses
from pipeline.kinematics import load_chain
from pipeline.orchestrator import RunConfig, run_pipeline
from pipeline.sim.scenario import scenario_from_dict
from pipeline.sim.simulator import write_recording

ROOT = Path(__file__).resolve().parents[1]
SEED = 7


def calibrate(
    work: Path,
    name: str,
    optics: dict[str, Any],
    touchup: dict[str, Any] | None = None,
    per_target: int = 8,
) -> dict[str, float]:
    raw = tomllib.loads((ROOT / "datasets" / "scenarios" / "standard.toml").read_text())
    raw["poses"]["per_target"] = per_target
    raw["optics"] = optics
    if touchup:
        raw["touchup"] = touchup
    sc = scenario_from_dict(raw, where=name, base_dir=str(ROOT))
    rec = work / f"{name}.mcap"
    truth = write_recording(sc, SEED, rec)
    out = work / name
    run_pipeline(rec, out, RunConfig(report=False), until="identify")
    base, flange = truth["base_link"], truth["flange_link"]
    cal = load_chain((out / "calibrated.urdf").read_text(), base, "virtual_pin")
    true_chain = load_chain(truth["true_urdf"], base, flange)
    inl = read_artefact(out / "inliers.parquet", "inliers")
    q = workspace_poses(inl[truth["joint_names"]].to_numpy(), 300, np.random.default_rng(SEED))
    acc = pin_accuracy(cal, np.zeros(3), true_chain, np.array(truth["p_vt_flange"]), q)
    ident = json.loads((out / "identify.json").read_text())
    return {
        "shape_mm": acc["shape_rms_m"] * 1e3,
        "kept": float(inl["inlier"].sum()),
        "n": float(len(inl)),
        "print_fitted": bool((ident.get("print_shape") or {}).get("fitted")),
    }


@pytest.fixture(scope="module")
def linear(tmp_path_factory: pytest.TempPathFactory) -> dict[str, float]:
    return calibrate(tmp_path_factory.mktemp("optics"), "linear", {})


def test_srgb_cell_calibrates_like_its_linear_twin(tmp_path: Path) -> None:
    # the standard cell's 36 touch-ups: with 24 the relative print sizes that absorb the
    # controller's per-target size-row error are not found (docs/detection.md, limits)
    linear36 = calibrate(tmp_path, "linear36", {}, per_target=12)
    srgb = calibrate(tmp_path, "srgb", {"response": "srgb"}, per_target=12)
    assert srgb["kept"] == srgb["n"]
    assert srgb["shape_mm"] <= 1.5 * linear36["shape_mm"], (srgb, linear36)


def test_unevenly_lit_cell_keeps_its_touchups(linear: dict[str, float], tmp_path: Path) -> None:
    uneven = calibrate(
        tmp_path,
        "uneven",
        {"illumination": 0.9, "sheen_grey": 25.0},
        touchup={"controller": "binary"},
    )
    assert uneven["kept"] >= uneven["n"] - 1, uneven
    assert uneven["shape_mm"] <= 0.1, (uneven, linear)


def test_out_of_round_prints_are_identified_and_calibrate(tmp_path: Path) -> None:
    prints = calibrate(tmp_path, "print", {"out_of_round_um": 20.0, "roughness_um": 2.0})
    assert prints["print_fitted"], prints
    assert prints["shape_mm"] <= 0.05, prints
