"""Guardrails: plausible-looking wrong inputs are refused with one line, not fitted.

Each case is seeded synthetic touch-ups of a perturbed LR Mate-like robot
(the nominal robot 1-2 mm off) with one wrong input. Before the guardrails,
each of them ended in a fit and a sub-0.1 mm residual claim.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_identify import LRMATE_CENTRE, PIN, _case

from pipeline.accuracy.evaluate import synthetic_touchups
from pipeline.errors import CalibrationFailed
from pipeline.guardrails import plausibility as pl
from pipeline.kinematics import load_chain
from pipeline.robots import builtin_urdf
from pipeline.stages.identify.stage import IdentifyConfig, conditioning_note, identify

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def cell():
    urdf, nominal, _, table, targets = _case(seed=4, per_target=10, noise_pin=10e-6)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    return urdf, nominal, table, d02


def _identify(cell, table=None, distance=None, accept=False):
    urdf, _, t, d02 = cell
    dist = [(0, 2, d02 if distance is None else distance)]
    cfg = IdentifyConfig(model="full", distances=dist, accept_implausible=accept)
    return identify(t if table is None else table, urdf, "base_link", "flange", cfg)


def test_the_right_inputs_pass(cell):
    res = _identify(cell)
    assert res.summary["implausible"] == []


def test_joint_values_in_degrees_are_refused(cell):
    _, nominal, table, _ = cell
    deg = table.copy()
    deg[nominal.joint_names] = np.rad2deg(deg[nominal.joint_names].to_numpy())
    with pytest.raises(CalibrationFailed, match="look like degrees") as exc:
        _identify(cell, table=deg)
    assert "--accept-implausible" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_swapped_joint_columns_outside_the_limits_are_refused(cell):
    _, nominal, table, _ = cell
    sw = table.copy()
    j = nominal.joint_names
    sw[[j[1], j[4]]] = sw[[j[4], j[1]]].to_numpy() * 3.0  # swapped and scaled: beyond limits
    lines = pl.joint_values(sw[j].to_numpy(), nominal)
    assert lines and all("outside the URDF's limits" in line for line in lines), lines
    assert all("check the joint columns" in line for line in lines), lines


@pytest.mark.parametrize(
    ("factor", "words"),
    [(1000.0, "millimetres"), (1.034, "typo"), (0.95, "typo")],
)
def test_a_wrong_bar_length_is_refused(cell, factor, words):
    _, _, _, d02 = cell
    with pytest.raises(CalibrationFailed, match=words) as exc:
        _identify(cell, distance=d02 * factor)
    assert "ppm" in str(exc.value)


def test_a_bar_within_the_nominal_robots_own_error_passes(cell):
    _, _, _, d02 = cell
    res = _identify(cell, distance=d02 * 1.002)  # 0.2 %: below what the nominal robot can tell
    assert res.summary["implausible"] == []


def test_accept_implausible_fits_and_keeps_the_lines(cell):
    _, _, _, d02 = cell
    res = _identify(cell, distance=d02 * 1.034, accept=True)
    assert len(res.summary["implausible"]) == 1
    assert "ppm" in res.summary["implausible"][0]


def test_the_nominal_fit_is_exact_on_the_nominal_robot():
    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(1)
    table, targets = synthetic_touchups(nominal, PIN, 3, 6, rng, q_centre=LRMATE_CENTRE)
    q = table[nominal.joint_names].to_numpy()
    tk = table["target_id"].to_numpy()
    pin, tg, rms = pl.nominal_targets(nominal, q, np.zeros((len(q), 3)), tk, 3, np.ones(len(q)))
    assert rms < 1e-9 and np.allclose(pin, PIN, atol=1e-9) and np.allclose(tg, targets, atol=1e-9)


def test_the_cli_exits_3_with_one_line(cell, tmp_path, capsys):
    from pipeline.cli import main

    urdf, nominal, table, d02 = cell
    csv = tmp_path / "t.csv"
    table.to_csv(csv, index=False)
    (tmp_path / "r.urdf").write_text(urdf)
    args = ["identify", str(csv), "--urdf", str(tmp_path / "r.urdf"), "--out",
            str(tmp_path / "o"), "--flange-link", "flange", "--base-link", "base_link",
            "--distance", f"0:2={d02 * 1000:.3f}", "--no-report", "--no-crossval"]  # fmt: skip
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "millimetres" in err[0], err


# -- wrong inputs that stay inside the joint limits (the nominal fit, the chain's ends) --------


def _refused(cell, table, match, **kw):
    urdf, _, _, d02 = cell
    cfg = IdentifyConfig(model="full", distances=[(0, 2, d02)], **kw)
    with pytest.raises(CalibrationFailed, match=match) as exc:
        identify(table, kw.pop("urdf", urdf), "base_link", kw.pop("flange", "flange"), cfg)
    assert "\n" not in str(exc.value) and "--accept-implausible" in str(exc.value)
    return str(exc.value)


@pytest.mark.parametrize("joint", [1, 2, 3])
def test_a_joint_with_its_sign_flipped_is_refused(cell, joint):
    _, nominal, table, _ = cell
    flipped = table.copy()
    name = nominal.joint_names[joint]
    flipped[name] = -flipped[name]
    assert not pl.joint_values(flipped[nominal.joint_names].to_numpy(), nominal)  # in limits
    msg = _refused(cell, flipped, "the nominal robot fits these touch-ups to")
    assert "mm RMS" in msg and "signs" in msg


def test_two_joint_columns_swapped_within_their_limits_are_refused(cell):
    _, nominal, table, _ = cell
    j = nominal.joint_names
    sw = table.copy()
    sw[[j[3], j[5]]] = sw[[j[5], j[3]]].to_numpy()
    assert not pl.joint_values(sw[j].to_numpy(), nominal)
    _refused(cell, sw, "the nominal robot fits these touch-ups to")


def test_touchups_labelled_with_the_wrong_target_are_refused(cell):
    _, _, table, _ = cell
    wrong = table.copy()
    tk = wrong["target_id"].to_numpy().copy()
    tk[np.flatnonzero(tk == 0)[:3]] = 1  # three touch-ups of target 0 filed under 1
    wrong["target_id"] = tk
    _refused(cell, wrong, "target labels")


def test_another_robots_urdf_is_refused(cell):
    _, nominal, table, d02 = cell
    ur = builtin_urdf("ur5e")
    other = load_chain(ur, "base_link", "flange")
    renamed = table.rename(columns=dict(zip(nominal.joint_names, other.joint_names, strict=True)))
    cfg = IdentifyConfig(model="full", distances=[(0, 2, d02)])
    with pytest.raises(CalibrationFailed, match="that the URDF is this robot's"):
        identify(renamed, ur, "base_link", "flange", cfg)


def test_a_flange_link_one_joint_short_is_refused(cell):
    urdf, nominal, table, d02 = cell
    cfg = IdentifyConfig(model="offsets", distances=[(0, 2, d02)])
    with pytest.raises(CalibrationFailed, match=r"joint joint_6 moves .* after the flange link"):
        identify(table, urdf, "base_link", "link_5", cfg)


def test_a_moving_joint_above_the_base_link_is_refused(cell):
    urdf, nominal, table, d02 = cell
    cfg = IdentifyConfig(model="offsets", distances=[(0, 2, d02)])
    with pytest.raises(CalibrationFailed, match=r"joint joint_1 moves .* above the base link"):
        identify(table, urdf, "link_1", "flange", cfg)


def test_an_equivalent_flange_link_passes(cell):
    urdf, _, table, d02 = cell  # link_6 -> flange is a fixed joint: the pin absorbs it
    res = identify(
        table, urdf, "base_link", "link_6", IdentifyConfig(model="full", distances=[(0, 2, d02)])
    )
    assert res.summary["implausible"] == []


@pytest.mark.parametrize(
    ("declared", "words"), [(10.0, "millimetres"), (0.0125, "typo"), (0.0101, None)]
)
def test_the_target_diameter_against_the_image_jacobian(declared, words):
    lines = pl.target_diameter(declared, 0.01003)
    if words is None:
        assert lines == []
    else:
        assert len(lines) == 1 and words in lines[0] and "image Jacobian" in lines[0]


def test_the_implied_diameter_matches_the_print_on_both_samples(tmp_path, conformance_sample):
    from pipeline.io.artefacts import read_meta
    from pipeline.run.orchestrator import run_pipeline

    sample = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
    for rec in (sample, conformance_sample):
        out = tmp_path / rec.stem
        run_pipeline(rec, out, until="touchups")
        implied = float(read_meta(out / "touchups.parquet")["implied_target_diameter_m"])
        assert abs(implied / 0.010 - 1.0) < 0.02, (rec.name, implied)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "target_diameter_m=10"], "target_diameter_m = 10 m"),
        (["--flange-link", "link_5"], "joint joint_6 moves"),
    ],
)
def test_the_run_refuses_a_wrong_diameter_or_flange_link(tmp_path, capsys, args, needle):
    from pipeline.cli import main

    sample = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
    with pytest.raises(SystemExit) as exc:
        main(["run", str(sample), "--out", str(tmp_path / "o"), "--no-report", "-q", *args])
    assert exc.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


@pytest.mark.parametrize(("spread", "weak"), [(0.35, False), (0.01, True)])
def test_a_weakly_excited_identification_says_so_with_its_figure(spread, weak):
    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(2)
    table, tg = synthetic_touchups(
        nominal, PIN, 3, 12, rng, spread_rad=spread, centre_spread_rad=spread,
        q_centre=LRMATE_CENTRE, noise_pin_m=5e-6,
    )  # fmt: skip
    d02 = float(np.linalg.norm(tg[0] - tg[2]))
    res = identify(table, urdf, "base_link", "flange", IdentifyConfig(model="full", distances=[(0, 2, d02)]))  # fmt: skip
    lines = [h for h in res.summary["headline"] if h.startswith("conditioning:")]
    if weak:
        # the figure is the fit's own (4.0e4-4.9e4 across numpy / scipy builds: the poses
        # barely excite the arm, which is the point)
        cond = float(res.summary["cond"])
        assert cond > 1e4
        assert len(lines) == 1 and f"cond {cond:.2e} > 1e+04" in lines[0], res.summary["headline"]
    else:
        assert lines == [] and res.summary["conditioning_note"].startswith("every identifiable")


def test_parameters_the_poses_do_not_excite_are_named():
    note, weak = conditioning_note(["joint_6.theta", "joint_6.d"], 18, 900.0)
    assert weak and "2 of 18 identifiable parameters are not excited" in note
    assert "joint_6.theta" in note and "> 1e+04" not in note
