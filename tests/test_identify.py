"""Identification: recovers known truth from seeded synthetic touch-ups, refuses clearly."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_accuracy,
    random_deviations,
    synthetic_touchups,
    workspace_poses,
)
from pipeline.errors import BadInput, CalibrationFailed
from pipeline.io.artefacts import read_artefact
from pipeline.kinematics import load_chain
from pipeline.robots import builtin_urdf
from pipeline.run.runner import write_fits
from pipeline.stages.identify.stage import IdentifyConfig, identify

PIN = np.array([0.0167, -0.0101, 0.2524])
LRMATE_CENTRE = np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32])


def _case(robot="lrmate", seed=0, n_targets=3, per_target=12, noise_q=0.0, noise_pin=0.0, dev=None):
    urdf = builtin_urdf(robot)
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(seed)
    deviations = dev if dev is not None else random_deviations(nominal, rng)
    true = perturbed_chain(nominal, deviations)
    centre = LRMATE_CENTRE if robot == "lrmate" else np.full(nominal.n_dof, 0.3)
    table, targets = synthetic_touchups(
        true,
        PIN,
        n_targets,
        per_target,
        rng,
        noise_q_rad=noise_q,
        noise_pin_m=noise_pin,
        q_centre=centre,
    )
    return urdf, nominal, true, table, targets


def _accuracy(result, true, table, nominal):
    qw = workspace_poses(table[nominal.joint_names].to_numpy(), 300, np.random.default_rng(9))
    return pin_accuracy(result.chain, result.p_flange_pin, true, PIN, qw)


@pytest.mark.parametrize("model", ["full", "mdh", "poe"])
def test_no_modelling_loss(model):
    urdf, nominal, true, table, targets = _case(seed=1)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    with_d = identify(
        table, urdf, "base_link", "flange", IdentifyConfig(model=model, distances=[(0, 2, d02)])
    )
    acc = _accuracy(with_d, true, table, nominal)
    assert acc["shape_max_m"] < 1e-6 and acc["abs_max_m"] < 1e-6, acc
    assert with_d.summary["scale_held"] is False
    assert (
        np.abs(
            with_d.targets[["x", "y", "z"]].to_numpy()[2]
            - with_d.targets[["x", "y", "z"]].to_numpy()[0]
        ).sum()
        > 0
    )
    without = identify(table, urdf, "base_link", "flange", IdentifyConfig(model=model))
    acc = _accuracy(without, true, table, nominal)
    assert acc["shape_max_m"] < 1e-6, acc
    assert without.summary["scale_held"] is True
    assert "held at the nominal" in without.summary["scale_note"]
    # nominal is millimetres off: the calibration did something
    nom = pin_accuracy(
        nominal,
        PIN,
        true,
        PIN,
        workspace_poses(table[nominal.joint_names].to_numpy(), 300, np.random.default_rng(9)),
    )
    assert nom["shape_rms_m"] > 2e-4


def test_no_modelling_loss_seven_axes():
    urdf, nominal, true, table, targets = _case(robot="iiwa7", seed=2, per_target=14)
    d01 = float(np.linalg.norm(targets[0] - targets[1]))
    r = identify(
        table, urdf, "base_link", "flange", IdentifyConfig(model="full", distances=[(0, 1, d01)])
    )
    acc = _accuracy(r, true, table, nominal)
    assert acc["shape_max_m"] < 1e-6 and acc["abs_max_m"] < 1e-6, acc


def test_offsets_model_recovers_pure_offsets():
    nominal = load_chain(builtin_urdf("lrmate"), "base_link", "flange")
    rng = np.random.default_rng(4)
    dev = {j: {"dq0_rad": float(rng.uniform(-2e-3, 2e-3))} for j in nominal.joint_names}
    urdf, nominal, true, table, _ = _case(seed=4, dev=dev, per_target=6)
    r = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="offsets"))
    acc = _accuracy(r, true, table, nominal)
    assert acc["shape_max_m"] < 1e-6, acc
    # identified offsets of the joints that are not gauge (joint_1 base, joint_6 pin)
    got = r.parameters.set_index("name")["value"]
    for j in ("joint_2", "joint_3", "joint_4", "joint_5"):
        assert got[f"{j}.dq0"] == pytest.approx(dev[j]["dq0_rad"], abs=1e-9)


def test_noisy_accuracy_and_covariance_prediction():
    # 72 touch-ups; encoder noise 1e-6 rad, pin contact noise 0.01 mm RMS (3D)
    urdf, nominal, true, table, targets = _case(
        seed=5, per_target=24, noise_q=1e-6, noise_pin=1e-5 / np.sqrt(3)
    )
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    r = identify(
        table, urdf, "base_link", "flange", IdentifyConfig(model="full", distances=[(0, 2, d02)])
    )
    acc = _accuracy(r, true, table, nominal)
    s = r.summary
    assert acc["shape_rms_m"] < 5e-5 and acc["shape_max_m"] < 1.5e-4, acc
    assert acc["abs_rms_m"] < 1.25 * acc["shape_rms_m"] + 2e-5, acc
    # the covariance predicts the random error within a factor of 3
    ratio = acc["shape_rms_m"] * 1e3 / s["predicted_shape_rms_mm"]
    assert 1 / 3 < ratio < 3, (acc, s["predicted_shape_rms_mm"])
    assert s["sigma_mm"] == pytest.approx(1e-2 / np.sqrt(3), rel=0.3)  # per-axis noise
    # standard errors and correlations are present for identified parameters only
    p = r.parameters
    assert p.loc[p.identifiable, "std"].notna().all()
    assert p.loc[~p.identifiable, "held_reason"].str.len().gt(0).all()
    corr = np.array(p.loc[p.identifiable | (p.kind == "pin"), "correlation"].tolist())
    assert np.allclose(np.diag(corr), 1.0) and np.allclose(corr, corr.T)
    for k in ("O1", "O2", "O3", "O4", "O5", "cond"):
        assert np.isfinite(s[k]) and s[k] > 0


def test_unused_rows_are_kept_with_reasons_and_string_labels():
    urdf, nominal, true, table, targets = _case(seed=6, per_target=10)
    d_ac = float(np.linalg.norm(targets[0] - targets[2]))
    table = table.copy()
    table["target_id"] = table["target_id"].map({0: "A", 1: "B", 2: "C"})
    table.loc[0, "converged"] = False
    table.loc[1, "weight"] = 0.0
    table["inlier"] = True
    table.loc[2, "inlier"] = False
    table.loc[2, "reason"] = "knocked"
    r = identify(table, urdf, "base_link", "flange", IdentifyConfig(distances=[("A", "C", d_ac)]))
    res = r.residuals
    assert len(res) == len(table)
    assert res.loc[0, "reason"] == "not converged" and not res.loc[0, "used"]
    assert "weight" in res.loc[1, "reason"]
    assert "knocked" in res.loc[2, "reason"]
    assert res["used"].sum() == len(table) - 3
    assert set(r.targets["target_label"]) == {"A", "B", "C"}
    assert np.isfinite(res.loc[0, "norm"])  # residual computed for an unused row too


def test_refusals():
    urdf, nominal, true, table, _ = _case(seed=7, per_target=10)
    with pytest.raises(CalibrationFailed, match="add at least"):
        identify(
            table[table.target_id == 0]
            .head(4)
            .pipe(lambda t: pd.concat([t, table[table.target_id == 1].head(3)])),
            urdf,
            "base_link",
            "flange",
            IdentifyConfig(model="full"),
        )
    with pytest.raises(CalibrationFailed, match="single target"):
        identify(table[table.target_id == 0], urdf, "base_link", "flange", IdentifyConfig())
    same = table.copy()
    same[nominal.joint_names] = table[nominal.joint_names].iloc[0].to_numpy()
    with pytest.raises(CalibrationFailed, match="same joint vector"):
        identify(same, urdf, "base_link", "flange", IdentifyConfig())
    with pytest.raises(BadInput, match="joint_3"):
        identify(table.drop(columns=["joint_3"]), urdf, "base_link", "flange", IdentifyConfig())
    with pytest.raises(BadInput, match="no target '7'"):
        identify(table, urdf, "base_link", "flange", IdentifyConfig(distances=[(0, 7, 0.5)]))
    with pytest.raises(BadInput, match="known"):
        identify(table, urdf, "base_link", "flange", IdentifyConfig(model="nope"))
    none = table.assign(converged=False)
    with pytest.raises(CalibrationFailed, match="no usable"):
        identify(none, urdf, "base_link", "flange", IdentifyConfig())


def test_all_models_and_outputs(tmp_path):
    urdf, nominal, true, table, targets = _case(seed=8, per_target=12, noise_q=1e-6, noise_pin=1e-5)
    results = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="all"))
    assert set(results) == {"full", "mdh", "poe", "offsets", "elastic", "elastic_mid"}
    paths = write_fits(results, tmp_path)
    params = read_artefact(paths["parameters"], "parameters")
    assert set(params.model) == set(results)
    read_artefact(paths["residuals"], "residuals")
    read_artefact(paths["targets"], "targets")
    summary = json.loads(paths["identify"].read_text())
    assert summary["scale_held"] is True and summary["best_model"] == "full"
    back = load_chain(paths["calibrated_urdf"].read_text(), "base_link", "virtual_pin")
    assert back.n_dof == 6
    # full, mdh and poe fit the same data equally well (same robot, complete models)
    rms = {k: r.summary["rms_mm"] for k, r in results.items()}
    assert abs(rms["full"] - rms["mdh"]) < 1e-3 and abs(rms["full"] - rms["poe"]) < 1e-3
    assert rms["offsets"] > 3 * rms["full"]


def test_auto_falls_back_to_offsets_when_too_few():
    urdf, nominal, true, table, _ = _case(seed=11, per_target=3)
    r = identify(table, urdf, "base_link", "flange", IdentifyConfig())
    assert r.model == "offsets"
    assert "fell back" in r.summary["model_choice"] and "add at least" in r.summary["headline"][1]
    more = identify(_case(seed=11, per_target=10)[3], urdf, "base_link", "flange", IdentifyConfig())
    assert more.model == "full" and more.summary["model_choice"] == "auto: full"


def test_robust_loss_downweights_a_bad_row():
    urdf, nominal, true, table, _ = _case(seed=9, per_target=14, noise_q=1e-6, noise_pin=1e-5)
    bad = table.copy()
    bad.loc[5, "joint_2"] += 2e-3  # a gross error of ~1 mm at the pin
    lin = identify(bad, urdf, "base_link", "flange", IdentifyConfig())
    rob = identify(
        bad, urdf, "base_link", "flange", IdentifyConfig(robust_loss="soft_l1", f_scale=3e-5)
    )
    assert rob.residuals["norm"].idxmax() == 5
    others = rob.residuals.drop(index=5)["norm"]
    assert others.max() < lin.residuals.drop(index=5)["norm"].max()


def test_cli_end_to_end(tmp_path, capsys):
    from pipeline.cli import main

    urdf, nominal, true, table, targets = _case(seed=10, per_target=10)
    csv = tmp_path / "t.csv"
    table.to_csv(csv, index=False)
    u = tmp_path / "robot.urdf"
    u.write_text(urdf)
    d = float(np.linalg.norm(targets[0] - targets[1]))
    main(
        [
            "identify",
            str(csv),
            "--urdf",
            str(u),
            "--out",
            str(tmp_path / "o"),
            "--distance",
            f"0:1={d}",
        ]
    )
    out = capsys.readouterr().out
    assert "length scale identified" in out
    assert (tmp_path / "o" / "calibrated.urdf").exists()
    with pytest.raises(SystemExit) as e:
        main(
            [
                "identify",
                str(csv),
                "--urdf",
                str(u),
                "--out",
                str(tmp_path / "p"),
                "--distance",
                "0:9=0.3",
            ]
        )
    assert e.value.code == 2
    assert "no target '9'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # a table that is not CSV/Parquet
        main(["identify", str(u), "--urdf", str(u), "--out", str(tmp_path / "p")])
    assert e.value.code == 2
    assert "must be .csv or .parquet" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # too few touch-ups: exit 3, says what to add
        table.groupby("target_id").head(3).to_csv(csv, index=False)
        main(
            [
                "identify",
                str(csv),
                "--urdf",
                str(u),
                "--out",
                str(tmp_path / "p"),
                "--model",
                "full",
            ]
        )
    assert e.value.code == 3
    assert "add at least" in capsys.readouterr().err


@pytest.mark.parametrize("loss", ["soft_l1", "huber", "cauchy", "arctan"])
def test_robust_losses_match_scipy_on_touchup_rows(loss):
    try:  # scipy's own implementations (private): the reference
        from scipy.optimize._lsq.least_squares import IMPLEMENTED_LOSSES
    except ImportError:
        pytest.skip("scipy's private loss table moved")

    from pipeline.estimation.loss import partial_loss

    z = np.linspace(0.0, 9.0, 40)
    ours = partial_loss(loss, 30)(z)
    ref = np.empty((3, 40))
    IMPLEMENTED_LOSSES[loss](z, ref, cost_only=False)
    assert np.allclose(ours[:, :30], ref[:, :30])
    assert np.allclose(ours[:, 30:], [z[30:], np.ones(10), np.zeros(10)])


def test_tool_link_as_flange():
    """A URDF that carries a tool link: name it, the pin is found in its frame."""
    urdf, nominal, true, table, targets = _case(seed=12, per_target=12)
    tool = (
        '<link name="tool0"/><joint name="tool_joint" type="fixed"><parent link="flange"/>'
        '<child link="tool0"/><origin xyz="0 0 0.1" rpy="0 0 0.5"/></joint></robot>'
    )
    urdf_tool = urdf.replace("</robot>", tool)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    r = identify(table, urdf_tool, "base_link", "tool0", IdentifyConfig(distances=[(0, 2, d02)]))
    tool_chain = load_chain(urdf_tool, "base_link", "tool0")
    # the pin in the tool frame: R_z(-0.5) (PIN - [0, 0, 0.1])
    c, s = np.cos(0.5), np.sin(0.5)
    want = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]) @ (PIN - [0, 0, 0.1])
    # (the pin itself trades with the last joint's slide along its axis: compare positions)
    assert np.allclose(r.p_flange_pin, want, atol=2e-3)
    back = load_chain(r.calibrated_urdf, "base_link", "virtual_pin")
    assert back.joints[-1].parent == "tool0"
    qw = workspace_poses(table[nominal.joint_names].to_numpy(), 200, np.random.default_rng(1))
    true_tool = true.with_tip(tool_chain.joints[-1].T_parent_joint, "tool0")
    assert pin_accuracy(r.chain, r.p_flange_pin, true_tool, want, qw)["abs_max_m"] < 1e-6


def test_runs_on_the_conformance_touchups(conformance_truth):
    """The independent writer's 12 touch-ups (10 converged): too few for the full model,
    so ``auto`` falls back to zero offsets and says why; nothing crashes."""
    t = conformance_truth
    rows = [
        {
            "touchup_id": tu["index"],
            "target_id": tu["label"],
            "converged": bool(tu["converged"]) and not tu.get("lost", False),
            **dict(zip(t["joint_names"], tu["q"], strict=True)),
        }
        for tu in t["touchups"]
    ]
    table = pd.DataFrame(rows)
    kd = t["known_distances"][0]
    r = identify(
        table,
        t["nominal_urdf"],
        t["base_link"],
        t["flange_link"],
        IdentifyConfig(distances=[(kd["labels"][0], kd["labels"][1], kd["metres"])]),
    )
    assert r.model == "offsets" and "fell back" in r.summary["model_choice"]
    assert r.summary["n_used"] == int(table.converged.sum())
    with pytest.raises(CalibrationFailed, match="add at least"):
        identify(
            table, t["nominal_urdf"], t["base_link"], t["flange_link"], IdentifyConfig(model="full")
        )


def test_design_jacobian_rates_pose_sets():
    from pipeline.models.observability import observability
    from pipeline.stages.identify.stage import design_jacobian

    urdf, nominal, true, table, targets = _case(seed=13, per_target=12)
    q = table[nominal.joint_names].to_numpy()
    tid = table["target_id"].to_numpy()
    Jk, Jn, names = design_jacobian(urdf, "base_link", "flange", q, tid, PIN, known_distance=True)
    assert Jk.shape == (3 * len(q) + 1, len(names)) and Jn.shape == (3 * len(q) + 1, 12)
    assert "joint_1.dx" not in names  # absorbed by the targets
    good = observability(Jk, Jn)
    # the same number of touch-ups with little orientation variety rates worse
    rng = np.random.default_rng(0)
    narrow, _ = synthetic_touchups(true, PIN, 3, 12, rng, q_centre=LRMATE_CENTRE, spread_rad=0.05)
    Jk2, Jn2, _ = design_jacobian(
        urdf,
        "base_link",
        "flange",
        narrow[nominal.joint_names].to_numpy(),
        narrow["target_id"].to_numpy(),
        PIN,
        known_distance=True,
    )
    bad = observability(Jk2, Jn2)
    assert bad["O1"] < good["O1"] and bad["O3"] < good["O3"]


def test_flange_frame_noise_model_beats_isotropic_on_anisotropic_noise():
    """Touch-ups are ~20x less precise along the view: weighing that in pays."""
    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(21)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    table, targets = synthetic_touchups(
        true,
        PIN,
        3,
        24,
        rng,
        noise_q_rad=1e-7,
        noise_flange_m=[1e-6, 1e-6, 2e-5],
        q_centre=LRMATE_CENTRE,
    )
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    acc = {}
    for nm in ("isotropic", "flange"):
        r = identify(
            table,
            urdf,
            "base_link",
            "flange",
            IdentifyConfig(distances=[(0, 2, d02)], noise_model=nm),
        )
        acc[nm] = _accuracy(r, true, table, nominal)["shape_rms_m"]
        if nm == "flange":
            sig = r.summary["flange_sigma_mm"]
            assert max(sig) > 5 * min(sig)  # it saw the anisotropy
    assert acc["flange"] < acc["isotropic"] / 1.5, acc


def test_the_fit_residual_is_the_pin_to_target_distance_not_the_whitened_residual():
    """identify.json's rms_mm is the RMS of residuals.parquet's distances (it was the
    whitened residual: 0.0134 mm against the report's 0.0199 mm on the shipped sample)."""
    urdf, nominal, true, table, targets = _case(seed=4, per_target=10, noise_pin=10e-6)
    # anisotropic noise: the flange-frame whitening is active and changes the residual vector
    rng = np.random.default_rng(3)
    table = table.copy()
    table["dz_flange"] = rng.normal(0.0, 40e-6, len(table))
    res = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="full"))
    assert "whitened" in res.summary["noise_model"]  # the case this test is about
    r = res.residuals[res.residuals["used"]]
    norms = np.linalg.norm(r[["rx", "ry", "rz"]].to_numpy(), axis=1)
    assert res.summary["rms_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(norms**2)), rel=1e-9)
    assert res.summary["max_mm"] == pytest.approx(1e3 * norms.max(), rel=1e-9)
