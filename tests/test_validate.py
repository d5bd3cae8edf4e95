"""vtcal validate: a calibration judged on touch-ups it was not fitted on.

Two seeded touch-up sets of the same simulated robot: calibrate on one, validate on
the other. The truth gives the reference: the true robot's own consistency on the
second set is what the touch-up noise alone leaves.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.evaluate import perturbed_chain, random_deviations, synthetic_touchups
from pipeline.accuracy.validate import Touchups, consistency, judge, usable_touchups
from pipeline.cli import main
from pipeline.kinematics import load_chain
from pipeline.kinematics.urdf_write import write_calibrated_urdf

REPO = Path(__file__).resolve().parent.parent
NOMINAL = (REPO / "pipeline/robots/lrmate.urdf").read_text()
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]
NOISE_M = 2e-5  # touch-up miss per axis


def vtcal(*args: str) -> int:
    """The CLI in process; its exit code."""
    try:
        main(list(args))
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Nominal and true robot, two recordings' tables, and a calibration on the first."""
    root = tmp_path_factory.mktemp("cell")
    nominal = load_chain(NOMINAL, "base_link", "flange")
    true = perturbed_chain(nominal, random_deviations(nominal, np.random.default_rng(7)))
    tables, dist = {}, {}
    for name, seed in (("a", 1), ("b", 2)):
        tab, tg = synthetic_touchups(
            true, PIN, 4, 10, np.random.default_rng(seed), noise_pin_m=NOISE_M,
            q_centre=Q_CENTRE, spread_rad=0.9, centre_spread_rad=0.9,
        )  # fmt: skip
        tables[name] = root / f"{name}.csv"
        tab.to_csv(tables[name], index=False)
        dist[name] = f"0:3={np.linalg.norm(tg[0] - tg[3]):.9f}"
    (root / "nominal.urdf").write_text(NOMINAL)
    code = vtcal(
        "identify", str(tables["a"]), "--urdf", str(root / "nominal.urdf"), "--out",
        str(root / "cal"), "--flange-link", "flange", "--model", "full", "--no-crossval",
        "--no-report", "--distance", dist["a"],
    )  # fmt: skip
    assert code == 0
    return {
        "root": root,
        "true": true,
        "tables": tables,
        "dist": dist,
        "nominal": root / "nominal.urdf",
        "calibrated": root / "cal" / "calibrated.urdf",
    }


def _validate(cell: dict, *extra: str, calibrated: Path | None = None) -> int:
    return vtcal(
        "validate", str(calibrated or cell["calibrated"]), str(cell["tables"]["b"]),
        "--urdf", str(cell["nominal"]), "--distance", cell["dist"]["b"], *extra,
    )  # fmt: skip


def test_calibrated_robot_is_consistent_on_a_recording_it_was_not_fitted_on(
    cell: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "val"
    assert _validate(cell, "--tolerance-mm", "0.2", "--out", str(out)) == 0
    res = json.loads((out / "validate.json").read_text())
    rows = {r["label"]: r for r in res["robots"]}
    after = rows["calibrated (its own pin)"]
    before = rows["nominal + refitted pin"]
    # the reference: the TRUE robot's consistency on the same touch-ups (noise alone)
    df = pd.read_csv(cell["tables"]["b"])
    data = usable_touchups(df, cell["true"].joint_names, "b")
    noise = judge("truth", cell["true"], PIN, data, [])["consistency_mm"]
    assert 0.5 * noise < after["consistency_mm"] < 1.5 * noise, (after, noise)
    assert before["consistency_mm"] > 10 * after["consistency_mm"]
    # the scale the calibration learnt from table a's bar, on table b's (noise alone: ~0.01 mm)
    assert after["distances"][0]["error_mm"] < 0.1
    v = res["verdict"]
    assert v["passed"] is True and v["improved"] is True and res["headline"] == after["label"]
    assert (
        v["validated_mm"] == after["consistency_mm"] and v["nominal_mm"] == before["consistency_mm"]
    )
    stdout = capsys.readouterr().out
    assert "| PASS (" in stdout and "nominal + refitted pin" in stdout
    page = (out / "validate.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "PASS" in page
    assert "http" not in page.split("</title>", 1)[1] and "<script" not in page


def test_tight_tolerance_fails_with_exit_3(cell: dict, capsys: pytest.CaptureFixture[str]) -> None:
    assert _validate(cell, "--tolerance-mm", "0.001") == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "FAIL" in err[0] and "> 0.001 mm" in err[0], err


def test_the_nominal_urdf_as_calibrated_is_not_improved(
    cell: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # without a pin: refitted (and said so); identical to the nominal row, so not improved
    assert _validate(cell, calibrated=cell["nominal"]) == 3
    cap = capsys.readouterr()
    assert "no virtual_pin_joint" in cap.out and "NOT improved" in cap.out
    assert len(cap.err.strip().splitlines()) == 1 and "NOT improved" in cap.err
    # with the true pin on the nominal kinematics and a loose tolerance: FAIL, not a PASS
    nominal_chain = load_chain(NOMINAL, "base_link", "flange")
    with_pin = tmp_path / "nominal_pin.urdf"
    with_pin.write_text(write_calibrated_urdf(NOMINAL, {}, "flange", PIN))
    assert _validate(cell, "--tolerance-mm", "50", calibrated=with_pin) == 3
    assert "| FAIL (not improved" in capsys.readouterr().out
    assert nominal_chain.n_dof == 6


def test_a_recording_is_validated_through_ingest_touchups_and_outliers(tmp_path: Path) -> None:
    """A small simulated recording, judged with its true robot (known distance from metadata)."""
    rec = tmp_path / "rec.mcap"
    scenario = tmp_path / "s.toml"
    scenario.write_text('name = "v"\n[robot]\nname = "lrmate"\n[targets]\ncount = 3\n'
                        "[poses]\nper_target = 3\n")  # fmt: skip
    assert vtcal("simulate", "--scenario", str(scenario), "--seed", "3", "--out", str(rec),
                 "--quiet") == 0  # fmt: skip
    truth = json.loads(Path(str(rec) + ".truth.json").read_text())
    (tmp_path / "true.urdf").write_text(truth["true_urdf_with_pin"])
    out = tmp_path / "val"
    args = ["validate", str(tmp_path / "true.urdf"), str(rec), "--out", str(out), "-q"]
    assert vtcal(*args, "--tolerance-mm", "0.1") == 0
    res = json.loads((out / "validate.json").read_text())
    assert {"frames.parquet", "inliers.parquet", "validate.html"} <= {p.name for p in out.iterdir()}
    after, before = res["robots"][0], res["robots"][-1]
    assert after["consistency_mm"] < 0.05 and before["consistency_mm"] > 0.3
    bar = truth["known_distances"][0]
    pair = f"{bar['labels'][0]}:{bar['labels'][1]}"
    assert [d["pair"] for d in after["distances"]] == [pair]
    assert after["distances"][0]["error_mm"] < 0.05
    assert before["distances"][0]["error_mm"] > 10 * after["distances"][0]["error_mm"]
    # again, into the same folder: the stages are reused; a tight tolerance FAILs with exit 3
    stamp = (out / "inliers.parquet").stat().st_mtime_ns
    assert vtcal(*args, "--tolerance-mm", "0.001") == 3
    assert (out / "inliers.parquet").stat().st_mtime_ns == stamp
    assert json.loads((out / "validate.json").read_text())["verdict"]["passed"] is False


def _one_line(capsys: pytest.CaptureFixture[str], *needles: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for n in needles:
        assert n in err[0], err
    return err[0]


def test_bad_inputs_are_one_line_and_nothing_is_written(
    cell: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "val"
    b = pd.read_csv(cell["tables"]["b"])
    # joint names of the input not in the calibrated URDF
    renamed = tmp_path / "renamed.csv"
    b.rename(columns={"joint_1": "J1"}).to_csv(renamed, index=False)
    code = vtcal("validate", str(cell["calibrated"]), str(renamed), "--urdf",
                 str(cell["nominal"]), "--out", str(out))  # fmt: skip
    assert code == 2
    _one_line(capsys, "renamed.csv", "joint_1")
    # fewer than 2 usable touch-ups of a target
    lonely = tmp_path / "lonely.csv"
    b[
        (b["target_id"] != 2) | (b["touchup_id"] == b[b["target_id"] == 2]["touchup_id"].min())
    ].to_csv(lonely, index=False)
    code = vtcal("validate", str(cell["calibrated"]), str(lonely), "--urdf",
                 str(cell["nominal"]), "--out", str(out))  # fmt: skip
    assert code == 3
    _one_line(capsys, "lonely.csv", "2 (1)", "fewer than 2")
    # a URDF without a chain from base to flange
    assert _validate(cell, "--flange-link", "no_such_link", "--out", str(out)) == 2
    _one_line(capsys, "calibrated.urdf", "no_such_link")
    # a table without a nominal URDF; a known distance naming no touched target
    code = vtcal("validate", str(cell["calibrated"]), str(cell["tables"]["b"]))
    assert code == 2
    _one_line(capsys, "b.csv", "--urdf")
    assert _validate(cell, "--distance", "0:9=0.5") == 2
    _one_line(capsys, "target '9'")
    assert not out.exists()


def test_consistency_and_distance_figures_from_known_points() -> None:
    """(V2)/(V3) on points whose spread is known by construction."""
    rng = np.random.default_rng(0)
    centres = rng.normal(0, 0.3, (3, 3))
    offsets = rng.normal(0, 1e-4, (30, 3))
    tk = np.repeat(np.arange(3), 10)
    for k in range(3):  # zero-mean offsets per target: the centres are exact
        offsets[tk == k] -= offsets[tk == k].mean(axis=0)
    got_c, dist, per = consistency(centres[tk] + offsets, tk, 3)
    np.testing.assert_allclose(got_c, centres, atol=1e-15)
    np.testing.assert_allclose(dist, np.linalg.norm(offsets, axis=1), atol=1e-15)
    for k in range(3):
        assert per[k] == pytest.approx(np.sqrt(np.mean(np.sum(offsets[tk == k] ** 2, 1))))
    # a chain whose flange sits at the base: FK = identity, so the pin points are the pins
    from pipeline.kinematics.chain import Chain
    from pipeline.kinematics.urdf import Joint

    j = Joint("j", "prismatic", "base", "flange", np.eye(4), np.array([0.0, 0.0, 1.0]))
    chain = Chain("base", "flange", (j,))
    data = Touchups(np.zeros((30, 1)), centres[tk] + offsets, tk, ["a", "b", "c"], 30, 0)
    D = float(np.linalg.norm(centres[0] - centres[2]))
    r = judge("x", chain, np.zeros(3), data, [("a", "c", D + 1e-4)])
    assert r["distances"][0]["error_mm"] == pytest.approx(0.1, abs=1e-9)
    assert r["consistency_mm"] == pytest.approx(np.sqrt(np.mean(dist**2)) * 1e3)


def test_real_panda_held_out_placement_matches_bench_real(tmp_path: Path) -> None:
    """MUKCa Panda data: train on one placement, validate on another; bench_real's KPIs agree."""
    spec = importlib.util.spec_from_file_location("bench_real", REPO / "benchmarks/bench_real.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_real"] = bench
    spec.loader.exec_module(bench)
    df = bench.load_table("panda_3")
    predict, _, _ = bench.vtcal_identify(df, ["frontcenter"], "full", tmp_path)
    reference = bench.Judge(df, ["frontcenter"]).predictor(predict)["backleft"]
    table = tmp_path / "backleft.csv"
    df[df["placement"] == "backleft"].drop(columns="placement").to_csv(table, index=False)
    out = tmp_path / "val"
    code = vtcal(
        "validate", str(tmp_path / "frontcenter_full" / "calibrated.urdf"), str(table),
        "--urdf", str(bench.DATA / "nominal_panda.urdf"), "--out", str(out),
        "--distance", "backleft/hole_0:backleft/hole_1=0.05",
    )  # fmt: skip
    assert code == 0
    after = json.loads((out / "validate.json").read_text())["robots"][0]
    assert after["consistency_mm"] == pytest.approx(reference.consistency_mm, rel=1e-9)
    assert after["distances"][0]["error_mm"] == pytest.approx(
        reference.distance_error_mm, rel=1e-6, abs=1e-9
    )


def test_the_table_it_was_fitted_on_is_refused(
    cell: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Judged on its own training touch-ups a calibration would show a training figure as
    validated (the provenance block names the source's hash; the same bytes are refused)."""
    copy = tmp_path / "same_bytes.csv"
    copy.write_bytes(cell["tables"]["a"].read_bytes())
    capsys.readouterr()
    code = vtcal(
        "validate", str(cell["calibrated"]), str(copy), "--urdf", str(cell["nominal"]),
        "--distance", cell["dist"]["a"], "--out", str(tmp_path / "v"),
    )  # fmt: skip
    assert code == 3
    _one_line(capsys, "was fitted on", "not a validation")
    assert not (tmp_path / "v").exists()
    assert _validate(cell) == 0, "another table of the same cell is judged as before"
