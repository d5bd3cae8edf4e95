"""The elastic error model: Jacobian, exactness of its parts, recovery of a simulated elastic arm."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.evaluate import registered_errors, synthetic_touchups, workspace_poses
from pipeline.kinematics import load_chain
from pipeline.kinematics.chain import fk_frames
from pipeline.models import get_model
from pipeline.models.elastic import G_BASE, LUMPED_MASS_KG, gravity_torque
from pipeline.robots import builtin_urdf
from pipeline.stages.crossval.stage import CrossvalConfig, cross_validate
from pipeline.stages.identify.stage import IdentifyConfig, identify

PIN = np.array([0.0167, -0.0101, 0.2524])
LRMATE_CENTRE = np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32])


def _chain(robot):
    return load_chain(builtin_urdf(robot), "base_link", "flange")


@pytest.mark.parametrize("robot", ["lrmate", "ur5e", "iiwa7"])
def test_jacobian_matches_finite_differences(robot):
    chain = _chain(robot)
    m = get_model("elastic")(chain)
    rng = np.random.default_rng(3)
    x = rng.normal(0, 0.01, m.n_params)
    x[m.n_kin :] = rng.normal(0, 1e-3, m.n_params - m.n_kin)  # deflections of ~0.01-0.1 rad
    q = rng.uniform(-1.5, 1.5, (10, chain.n_dof))
    pf = rng.normal(0, 0.1, (10, 3))
    _, _, J = m.pin_and_jacobian(x, q, pf)
    for i in range(m.n_params):
        h = 1e-6 if i < m.n_kin else 1e-8
        e = np.zeros(m.n_params)
        e[i] = h
        fd = (
            m.pin_and_jacobian(x + e, q, pf, jac=False)[0]
            - m.pin_and_jacobian(x - e, q, pf, jac=False)[0]
        ) / (2 * h)
        scale = 1.0 + np.abs(fd).max()
        assert np.abs(J[:, :, i] - fd).max() < 1e-6 * scale, m.param_names[i]


def test_gravity_torque_against_an_independent_sum():
    """(E2) by brute force: each mass's moment about each joint, from fk_frames alone."""
    chain = _chain("ur5e")
    rng = np.random.default_rng(4)
    q = rng.uniform(-2, 2, (6, chain.n_dof))
    T_tip, F = fk_frames(chain, q)
    tau = gravity_torque(chain, q)
    n = chain.n_dof
    for i in range(len(q)):
        masses = [F[i, k, :3, 3] for k in range(n)] + [T_tip[i, :3, 3]]
        for j, joint in enumerate(chain.actuated):
            a = F[i, j, :3, :3] @ np.asarray(joint.axis)
            ref = sum(
                float(a @ np.cross(p - F[i, j, :3, 3], LUMPED_MASS_KG * G_BASE))
                for p in masses[j + 1 :]
            )
            assert tau[i, j] == pytest.approx(ref, abs=1e-12)
    # UR5e: the first axis is vertical, so gravity exerts no torque about it
    assert np.abs(tau[:, 0]).max() < 1e-12


def test_rigid_part_is_full_and_zero_compliance_is_full():
    chain = _chain("lrmate")
    el, full = get_model("elastic")(chain), get_model("full")(chain)
    assert el.param_names[: el.n_kin] == full.param_names and not el.urdf_exact
    assert all(u == "rad/(N m)" for u in el.param_units[el.n_kin :])
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(0, 0.003, el.n_kin), np.zeros(el.n_params - el.n_kin)])
    q = rng.uniform(-2, 2, (20, chain.n_dof))
    p_el = el.pin_and_jacobian(x, q, PIN, jac=False)[0]
    p_full = full.pin_and_jacobian(x[: el.n_kin], q, PIN, jac=False)[0]
    assert np.abs(p_el - p_full).max() < 1e-15
    x[el.n_kin + 1] = 1e-4
    o_el, o_full = el.origins(x), full.origins(x[: el.n_kin])
    assert all(np.array_equal(o_el[k], o_full[k]) for k in o_full)


def _elastic_case(seed, c_true, noise_pin=0.0):
    """Touch-ups of an arm whose joints deflect by c_j tau_j(q) on top of full-model errors.

    The true joint angles ``q'`` come from exact touch-ups of the true rigid part;
    the encoder reads ``q`` with ``q + c tau(q) = q'`` (fixed point of (E1)).
    """
    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    m = get_model("elastic")(nominal)
    rng = np.random.default_rng(seed)
    x_true = np.concatenate([rng.normal(0, 4e-4, m.n_kin), c_true])
    table, targets = synthetic_touchups(
        m.chain(x_true), PIN, 3, 14, rng, q_centre=LRMATE_CENTRE, noise_pin_m=noise_pin
    )
    names = nominal.joint_names
    q_true = table[names].to_numpy()
    q = q_true.copy()
    for _ in range(50):
        q = q_true - m.deflection(x_true, q)
    table[names] = q
    return urdf, m, x_true, table, targets


def test_recovers_a_simulated_elastic_robot():
    c_true = np.array([0.0, 6e-5, 9e-5, 4e-5, 3e-5, 0.0])
    urdf, m, x_true, table, targets = _elastic_case(11, c_true)
    d = float(np.linalg.norm(targets[0] - targets[1]))
    cfg = IdentifyConfig(model="elastic", distances=[(0, 1, d)])
    res = identify(table, urdf, "base_link", "flange", cfg)
    qw = workspace_poses(table[m.nominal.joint_names].to_numpy(), 300, np.random.default_rng(9))
    p_fit = res.predict(qw, np.zeros((len(qw), 3)))
    p_true = m.pin_and_jacobian(x_true, qw, PIN, jac=False)[0]
    assert registered_errors(p_fit, p_true, scale=False).max() < 1e-6
    ident = res.parameters.set_index("name")
    for j, name in enumerate(m.nominal.joint_names):
        row = ident.loc[f"{name}.compliance"]
        if row["identifiable"]:
            assert row["value"] == pytest.approx(c_true[j], rel=1e-4, abs=1e-9), name
    # the lumped masses exert torque about joints 2-5 of the LR Mate: those are identified
    assert ident.loc[[f"joint_{k}.compliance" for k in (2, 3, 4, 5)], "identifiable"].all()
    # joint 1 is vertical: no torque, held with a reason
    assert not ident.loc["joint_1.compliance", "identifiable"]
    # the rigid model cannot follow the deflection
    full = identify(
        table, urdf, "base_link", "flange", IdentifyConfig(model="full", distances=cfg.distances)
    )
    assert full.summary["rms_mm"] > 20 * res.summary["rms_mm"]
    assert "rigid part only" in res.summary["urdf_note"]


def test_no_loss_on_a_rigid_robot():
    """Compliance ~ 0 on a rigid arm, and accuracy within noise of the full model."""
    zero = np.zeros(6)
    urdf, m, x_true, table, targets = _elastic_case(12, zero, noise_pin=2e-5)
    d = float(np.linalg.norm(targets[0] - targets[1]))
    qw = workspace_poses(table[m.nominal.joint_names].to_numpy(), 300, np.random.default_rng(9))
    p_true = m.pin_and_jacobian(x_true, qw, PIN, jac=False)[0]
    errs = {}
    for name in ("full", "elastic"):
        r = identify(
            table, urdf, "base_link", "flange", IdentifyConfig(model=name, distances=[(0, 1, d)])
        )
        e = registered_errors(r.predict(qw, np.zeros((len(qw), 3))), p_true, scale=False)
        errs[name] = float(np.sqrt(np.mean(e**2)))
        if name == "elastic":
            c = r.parameters.set_index("name").filter(like=".compliance", axis=0)
            c = c[c["identifiable"]]
            # every compliance is zero within 4 standard errors
            assert len(c) >= 4 and (c["value"].abs() < 4 * c["std"]).all(), c[["value", "std"]]
    assert errs["elastic"] < 2.0 * errs["full"] + 5e-6, errs


def test_crossval_never_ships_the_elastic_urdf_over_a_rigid_one():
    c_true = np.array([0.0, 6e-5, 9e-5, 4e-5, 3e-5, 0.0])
    urdf, m, x_true, table, targets = _elastic_case(13, c_true, noise_pin=1e-6)
    d = float(np.linalg.norm(targets[0] - targets[1]))
    cfg = IdentifyConfig(model="all", distances=[(0, 1, d)])
    cv = cross_validate(
        table,
        urdf,
        "base_link",
        "flange",
        cfg,
        CrossvalConfig(models=["full", "elastic"], loto=False),
    )
    s = cv.summary
    assert s["best_predictor"] == "elastic"
    assert s["models"]["elastic"]["kfold_rms_mm"] < 0.5 * s["models"]["full"]["kfold_rms_mm"]
    assert cv.chosen_model == "full"
    assert "URDF cannot carry" in s["choice"]
