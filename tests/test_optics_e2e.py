"""End to end on images formed as real cameras form them (issue 14).

Twins of one simulated cell (same seed: same robot, targets, plan and noise
draws), each calibrated by the whole pipeline and judged against the truth:

* sRGB-encoded images calibrate within 1.5x of the linear twin on the standard
  cell's 36 touch-ups, seed 7 (before vtcal linearised its grey levels, every long
  axis read ~0.4-0.8 px short and the pin sat millimetres off along the view:
  ~1.2 mm here). The controller's own detector reads the encoded image ~0.43 px
  short, so every touch-up is corrected by ~1.4 mm along the view; what is left is
  the encoded image's ~1.5x long-axis noise (docs/detection.md);
* uneven light with a controller whose simpler detector it fools (binary blob
  moments at one global threshold, ~1.5 px short and a few tenths of a pixel off
  centre) keeps its touch-ups (before: 17 of 18 rejected as "not converged") and
  calibrates to under 0.1 mm (~4.7 mm of along-view correction per touch-up);
* prints 20 um out of round (2 um rough) calibrate to under 0.05 mm, with the print
  shape identified (without the print-shape fit the same cell is 0.13 mm off with
  36 touch-ups: the long axis follows the camera's roll).

The figures per effect and seed are bench_optics' (docs/detection.md, "Real
cameras end to end", where what limits the first two is written up).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.accuracy.evaluate import pin_accuracy, workspace_poses
from pipeline.io.artefacts import read_artefact
from pipeline.kinematics import fk, load_chain
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.sim.scenario import scenario_from_dict
from pipeline.sim.simulator import write_recording
from pipeline.stages.ingest.stage import RecordingInfo
from pipeline.stages.touchups.stage import TouchupConfig, extract_touchups

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


def test_srgb_corrections_agree_across_targets(tmp_path: Path) -> None:
    """One image Jacobian for every target: the corrected pins agree target by target.

    On sRGB images the simulated controller stops every touch-up ~0.4 px of long
    axis short of vtcal's measure, so every touch-up is corrected by ~1.4 mm along
    the view. Against the truth (true robot, true pin, true target centres), each
    target's mean miss of the corrected pin across the view must be common to all
    targets (the pin takes a common part). With a full Jacobian per target (the
    old rule, ``jacobian='target'``) each target had its own 5-17 um (seed 9, 24
    touch-ups): offsets no kinematic parameter takes (docs/detection.md).
    """
    raw = tomllib.loads((ROOT / "datasets" / "scenarios" / "standard.toml").read_text())
    raw["poses"]["per_target"] = 8
    raw["optics"] = {"response": "srgb"}
    sc = scenario_from_dict(raw, where="srgb9", base_dir=str(ROOT))
    rec = tmp_path / "srgb9.mcap"
    truth = write_recording(sc, 9, rec)
    out = tmp_path / "srgb9"
    run_pipeline(rec, out, RunConfig(report=False), until="touchups")
    info = RecordingInfo(**json.loads((out / "recording.json").read_text()))
    frames = read_artefact(out / "frames.parquet", "frames")
    dets = read_artefact(out / "detections.parquet", "detections")
    chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    p_pin = np.array(truth["p_vt_flange"])
    centres = np.array([t["centre"] for t in truth["targets"]])

    def spreads(jacobian: str) -> tuple[float, float, float]:
        tab = extract_touchups(frames, dets, info, TouchupConfig(jacobian=jacobian))
        tab = tab[tab["converged"] & ~tab["lost"]]
        T = fk(chain, tab[list(info.joint_names)].to_numpy(dtype=float))
        d = tab[["dx_flange", "dy_flange", "dz_flange"]].to_numpy(dtype=float)
        hit = np.einsum("nij,nj->ni", T[:, :3, :3], p_pin + d) + T[:, :3, 3]
        tid = np.argmin(np.linalg.norm(hit[:, None] - centres[None], axis=2), axis=1)
        need = np.einsum("nji,nj->ni", T[:, :3, :3], centres[tid] - T[:, :3, 3]) - p_pin
        err = d - need  # flange frame, m
        g = tab[["view_gx", "view_gy", "view_gz"]].to_numpy(dtype=float)[0]
        g = g / np.linalg.norm(g)
        across = err - np.outer(err @ g, g)
        means = np.array([across[tid == k].mean(axis=0) for k in np.unique(tid)])
        along = np.array([(err @ g)[tid == k].mean() for k in np.unique(tid)])
        mean_d = float(np.linalg.norm(d, axis=1).mean())
        return (
            float(np.linalg.norm(means - means.mean(axis=0), axis=1).max()),
            float(np.ptp(along)),
            mean_d,
        )

    across, along, mean_d = spreads("global")
    assert mean_d > 0.8e-3  # the controller did stop off in size
    assert across < 2e-6, across
    assert along < 12e-6, along
    across_old, _, _ = spreads("target")
    assert across_old > 2 * across  # the test tells the rules apart
