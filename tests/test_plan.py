"""Measuring-pose planner: candidates, the rank-3 information update, selection, order, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from pipeline.cli import cli, main
from pipeline.errors import BadInput
from pipeline.io.artefacts import read_artefact
from pipeline.kinematics.chain import fk, load_chain
from pipeline.plan.candidates import CandidateConfig, generate_candidates, working_radius
from pipeline.plan.check import calibrate_and_score, touchups_at, true_world
from pipeline.plan.design import build_design
from pipeline.plan.ik import rotation_log, solve_ik_batch
from pipeline.plan.order import order_visits, path_length, travel_costs
from pipeline.plan.planner import PlanConfig, plan_poses
from pipeline.plan.select import SelectionState, criterion_value, select_poses
from pipeline.plan.targets import PlanTargets, read_targets, targets_from_frame
from pipeline.robots import load_urdf

REPO = Path(__file__).resolve().parents[1]
PIN = (0.03, 0.0, 0.25)


@pytest.fixture(scope="module")
def lrmate() -> tuple[str, PlanTargets]:
    return load_urdf("lrmate"), read_targets(REPO / "datasets/targets/lrmate_cell.csv")


@pytest.fixture(scope="module")
def small_design(lrmate: tuple[str, PlanTargets]):  # type: ignore[no-untyped-def]
    urdf, tg = lrmate
    chain = load_chain(urdf, "base_link", "flange")
    cs = generate_candidates(chain, tg, CandidateConfig(n_candidates=240, p_flange_pin=PIN))
    d = build_design(chain, "full", cs.q, cs.target_index, len(tg), PIN, working_radius(tg.centres))
    return chain, cs, d


# ----------------------------------------------------------------------------- targets


def test_targets_bad_input_names_the_problem(tmp_path: Path) -> None:
    ok = {"target_id": [0, 1], "x": [0.4, 0.4], "y": [0, 0.2], "z": [0.1, 0.1]}
    ok |= {"nx": [0, 0], "ny": [0, 0], "nz": [1, 1]}
    t = targets_from_frame(pd.DataFrame(ok))
    assert t.ids.tolist() == [0, 1] and np.allclose(np.linalg.norm(t.normals, axis=1), 1)
    with pytest.raises(BadInput, match="missing column"):
        targets_from_frame(pd.DataFrame(ok).drop(columns="nz"), "t.csv")
    with pytest.raises(BadInput, match="target_id 0 appears more than once"):
        targets_from_frame(pd.DataFrame(ok | {"target_id": [0, 0]}))
    with pytest.raises(BadInput, match="target 1: plate normal"):
        targets_from_frame(pd.DataFrame(ok | {"nz": [1, 0]}))
    with pytest.raises(BadInput, match="not found"):
        read_targets(tmp_path / "nope.csv")


# ----------------------------------------------------------------------------- IK, candidates


def test_rotation_log_matches_scipy() -> None:
    rv = Rotation.random(50, random_state=1).as_rotvec()
    rv[0] = [np.pi - 1e-12, 0, 0]
    R = Rotation.from_rotvec(rv).as_matrix()
    got = rotation_log(R)
    back = Rotation.from_rotvec(got).as_matrix()
    assert np.allclose(back, R, atol=1e-9)


def test_batch_ik_reaches_poses_inside_limits(lrmate: tuple[str, PlanTargets]) -> None:
    chain = load_chain(lrmate[0], "base_link", "flange")
    rng = np.random.default_rng(3)
    q_true = rng.uniform(chain.lower * 0.6, chain.upper * 0.6, (40, chain.n_dof))
    T = fk(chain, q_true)
    q, ok = solve_ik_batch(chain, T, q_true + rng.normal(0, 0.2, q_true.shape))
    assert ok.mean() > 0.9
    assert np.allclose(fk(chain, q[ok]), T[ok], atol=1e-8)
    assert np.all((q >= chain.lower) & (q <= chain.upper))


def test_candidates_put_pin_on_target_within_cone(small_design) -> None:  # type: ignore[no-untyped-def]
    chain, cs, _ = small_design
    acc = cs.accepted
    assert len(acc) > 150
    T = fk(chain, cs.q)
    tg = read_targets(REPO / "datasets/targets/lrmate_cell.csv")
    pins = T[:, :3, :3] @ np.array(PIN) + T[:, :3, 3]
    assert np.allclose(pins, tg.centres[cs.target_index], atol=1e-6)
    w = acc[["view_x", "view_y", "view_z"]].to_numpy()
    cosang = np.sum(w * tg.normals[cs.target_index], axis=1)
    assert np.all(cosang >= np.cos(np.deg2rad(35.0)) - 1e-9)
    # camera (flange z) looks along -w
    assert np.allclose(T[:, :3, 2], -w, atol=1e-7)
    # every candidate is accounted for: accepted or a reason
    assert set(cs.table.loc[~cs.table["accepted"], "reason"]) <= {
        "out of reach",
        "no IK solution",
        "joint limit margin",
        "near singularity",
    }


# ----------------------------------------------------------------------------- information


def test_rank3_update_equals_direct_schur_complement(small_design) -> None:  # type: ignore[no-untyped-def]
    _, _, d = small_design
    rng = np.random.default_rng(0)
    sel = rng.choice(len(d), 15, replace=False).tolist()
    st = SelectionState(d, sel, 0.0)
    cand = np.array([c for c in rng.choice(len(d), 6, replace=False) if c not in sel])
    At, C = st.update_terms(cand)
    gD = st.add_gains(cand, "O1")
    gA = st.add_gains(cand, "A")
    for b, c in enumerate(cand):
        S1 = d.schur(d.information(sel + [int(c)]))
        assert np.allclose(S1, st.S + At[b].T @ C[b] @ At[b], rtol=1e-9, atol=1e-9 * abs(S1).max())
        dD = criterion_value(S1, "O1") - criterion_value(st.S, "O1")
        dA = criterion_value(S1, "A") - criterion_value(st.S, "A")
        assert gD[b] == pytest.approx(float(dD), rel=1e-8)
        assert gA[b] == pytest.approx(float(dA), rel=1e-7)


def test_schur_eigenvalues_are_observability_singular_values(small_design) -> None:  # type: ignore[no-untyped-def]
    _, _, d = small_design
    idx = np.arange(0, len(d), 7)
    lam = np.linalg.eigvalsh(d.schur(d.information(idx)))
    obs = d.indices(idx)
    assert np.sqrt(lam[0]) == pytest.approx(obs["O3"], rel=1e-6)
    assert np.sqrt(lam[-1]) / np.sqrt(lam[0]) == pytest.approx(obs["cond"], rel=1e-6)


@pytest.mark.parametrize("criterion", ["O1", "O3", "O4", "A"])
def test_selection_beats_random_subsets(small_design, criterion: str) -> None:  # type: ignore[no-untyped-def]
    _, _, d = small_design
    sel = select_poses(d, 15, criterion)
    assert len(np.unique(sel.chosen)) == 15
    assert sel.value >= sel.start_value - 1e-12
    rng = np.random.default_rng(1)
    rand = [
        float(
            criterion_value(
                d.schur(d.information(rng.choice(len(d), 15, replace=False))), criterion
            )
        )
        for _ in range(20)
    ]
    assert sel.value > max(rand)


# ----------------------------------------------------------------------------- order


def test_order_is_a_shorter_permutation() -> None:
    rng = np.random.default_rng(2)
    q = rng.uniform(-2, 2, (30, 6))
    tk = rng.integers(0, 3, 30)
    o = order_visits(q, tk, switch_cost=0.5)
    assert sorted(o.tolist()) == list(range(30))
    D = travel_costs(q, tk, 0.5)
    assert path_length(D, o) < path_length(D, np.arange(30))
    # 2-opt optimum: no single reversal shortens it further
    best = path_length(D, o)
    for i in range(1, 29):
        for j in range(i + 1, 30):
            p = o.copy()
            p[i : j + 1] = p[i : j + 1][::-1]
            assert path_length(D, p) >= best - 1e-9


# ----------------------------------------------------------------------------- planner, refusals


def test_unreachable_target_is_named(lrmate: tuple[str, PlanTargets]) -> None:
    urdf, tg = lrmate
    far = PlanTargets(
        ids=np.array([0, 7]),
        centres=np.array([tg.centres[0], [3.0, 0.0, 0.2]]),
        normals=np.array([tg.normals[0], [0.0, 0.0, 1.0]]),
    )
    with pytest.raises(
        BadInput, match=r"target 7 at \[3.0, 0.0, 0.2\] m has no usable .*out of reach"
    ):
        plan_poses(urdf, far, PlanConfig(n_poses=6, n_candidates=40, p_flange_pin=PIN))


def test_empty_candidate_set_is_bad_input(lrmate: tuple[str, PlanTargets]) -> None:
    urdf, _ = lrmate
    none = PlanTargets(
        ids=np.array([4]), centres=np.array([[0.0, 0.0, 3.0]]), normals=np.eye(3)[2:]
    )
    with pytest.raises(BadInput, match="no usable measuring pose among 20 candidates"):
        plan_poses(urdf, none, PlanConfig(n_poses=6, n_candidates=20, p_flange_pin=PIN))
    with pytest.raises(BadInput, match="cone-deg"):
        plan_poses(urdf, none, PlanConfig(cone_deg=85.0))


def test_planned_poses_recover_known_truth(lrmate: tuple[str, PlanTargets]) -> None:
    """Exact touch-ups at planned poses calibrate a deviated robot to its shape exactly; with
    noise the error is of the size the plan predicts."""
    urdf, tg = lrmate
    res = plan_poses(urdf, tg, PlanConfig(n_poses=24, n_candidates=300, p_flange_pin=PIN, seed=3))
    cs, d = res.candidates, res.design
    pos = {c: i for i, c in enumerate(cs.accepted["candidate_id"].tolist())}
    idx = np.array([pos[c] for c in res.table["candidate_id"]])
    rng = np.random.default_rng(11)
    chain_t, pin_t, tg_t = true_world(d.model.nominal, PIN, tg.centres, rng)
    exact = touchups_at(
        chain_t, pin_t, tg_t, cs.q[idx], cs.target_index[idx], rng, noise_pin_m=0.0, noise_q_rad=0.0
    )
    assert exact["converged"].all()
    acc = calibrate_and_score(exact, urdf, chain_t, pin_t, res.eval_q)
    assert acc["shape_rms_m"] < 1e-7
    noisy = touchups_at(chain_t, pin_t, tg_t, cs.q[idx], cs.target_index[idx], rng)
    acc = calibrate_and_score(noisy, urdf, chain_t, pin_t, res.eval_q)
    pred = res.summary["predicted_shape_rms_mm"] * 1e-3
    assert 0.3 * pred < acc["shape_rms_m"] < 3.0 * pred


def test_cli_plan_feeds_the_simulator(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "plan.parquet"
    r = CliRunner().invoke(
        cli,
        [
            "plan", "--urdf", "lrmate", "--targets", str(REPO / "datasets/targets/lrmate_cell.csv"),
            "--poses", "9", "--candidates", "150", "--pin", "0.03,0,0.25", "--out", str(out),
            "--model", "offsets",  # 9 poses are too few for the full model (refused: rank)
        ],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "O1" in r.output and "predicted" in r.output
    df = read_artefact(out, "plan")
    assert len(df) == 9 and df["order"].tolist() == list(range(9))
    meta = pq.read_schema(out).metadata
    summary = json.loads(meta[b"vtcal.plan"])
    assert summary["indices_after"]["O1"] > 0 and summary["predicted_shape_rms_mm"] > 0

    import dataclasses

    from pipeline.sim.cell import build_cell
    from pipeline.sim.poses import measuring_poses
    from pipeline.sim.scenario import load_scenario

    sc = load_scenario(REPO / "datasets/scenarios/small.toml")
    sc = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, plan=str(out)))
    rng = np.random.default_rng(0)
    cell = build_cell(sc, rng)
    poses = measuring_poses(sc, cell, rng)
    assert [t for t, _ in poses] == df["target_id"].tolist()
    assert np.allclose(np.array([q for _, q in poses]), df[cell.nominal.joint_names].to_numpy())

    with pytest.raises(SystemExit) as exc:
        main(["plan", "--urdf", "lrmate", "--targets", str(tmp_path / "x.csv"), "--poses", "3",
              "--out", str(out)])  # fmt: skip
    assert exc.value.code == 2
    assert "targets file not found" in capsys.readouterr().err


def test_a_rank_deficient_plan_is_refused_not_written(tmp_path: Path, capsys) -> None:
    """5 poses for the full model: condition 2e17, and a 0.025 mm 'predicted error' before."""
    out = tmp_path / "p5.parquet"
    with pytest.raises(SystemExit) as exc:
        main(["plan", "--urdf", "lrmate", "--targets", str(REPO / "datasets/targets/lrmate_cell.csv"),
              "--poses", "5", "--candidates", "300", "--out", str(out)])  # fmt: skip
    assert exc.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rank deficient" in err[0] and "plan more poses" in err[0], err
    assert not out.exists()


def test_the_readme_plan_simulate_run_sequence_calibrates(tmp_path: Path, capsys) -> None:
    """README: plan (with the standard cell's pin) -> simulate -> run ends in a calibration.

    The README's 36 poses, simulated with seed 1: there one loop's first step is a 33 mm
    translation, which once split a touch-up in two (see below). Without --pin the
    planner's default pin is 69 mm from the cell's: simulate now refuses that plan
    (before, 34 of 36 touch-ups were lost and the run ended in exit 3).
    """
    import re

    readme = (REPO / "README.md").read_text()
    pin = re.search(r"vtcal plan --urdf lrmate [^`]*--pin ([0-9.,-]+)", readme)
    assert pin, "the README's plan example gives --pin"
    plan = tmp_path / "plan.parquet"
    targets = str(REPO / "datasets/targets/lrmate_cell.csv")
    main(["plan", "--urdf", "lrmate", "--targets", targets, "--poses", "36",
          "--pin", pin.group(1), "--out", str(plan)])  # fmt: skip
    rec = tmp_path / "rec.mcap"
    scen = str(REPO / "datasets/scenarios/standard.toml")
    main(["simulate", "--scenario", scen, "--plan", str(plan), "--out", str(rec), "--quiet",
          "--seed", "1"])  # fmt: skip
    main(["run", str(rec), "--out", str(tmp_path / "run"), "-q", "--no-report",
          "--until", "identify"])  # fmt: skip
    summary = json.loads((tmp_path / "run" / "identify.json").read_text())
    assert summary["n_used"] >= 34, summary["n_used"]
    # the touch-ups carry the simulator's target labels (first-touch order): a loop whose
    # first step was a long translation once split off a one-capture "touch-up" with a
    # label of its own, and the recording's bar 0:2 then named the wrong target
    truth = json.loads((tmp_path / "rec.mcap.truth.json").read_text())
    table = pd.read_parquet(tmp_path / "run" / "touchups.parquet")
    assert list(table["target_id"]) == [t["label"] for t in truth["touchups"]]
    assert summary["distances_dropped"] == [] and summary["scale_held"] is False
    # the planner's default pin: refused by simulate with one line naming the pin to use
    bad = tmp_path / "default_pin.parquet"
    main(["plan", "--urdf", "lrmate", "--targets", targets, "--poses", "18", "--out", str(bad)])
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", scen, "--plan", str(bad), "--out",
              str(tmp_path / "x.mcap"), "--quiet"])  # fmt: skip
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "plan with --pin" in err and not (tmp_path / "x.mcap").exists()
