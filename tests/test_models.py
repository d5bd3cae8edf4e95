"""Error models: analytic Jacobians equal finite differences, URDF write-back is exact."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.evaluate import pin_positions
from pipeline.errors import BadInput
from pipeline.kinematics import fk, load_chain
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.models import get_model, model_names
from pipeline.models.base import so3_exp, so3_right_jacobian
from pipeline.models.observability import indices_from_singular_values, observability
from pipeline.robots import builtin_urdf

ROBOTS = ["lrmate", "ur5e", "iiwa7"]


def _chain(robot):
    return load_chain(builtin_urdf(robot), "base_link", "flange")


def test_registry_has_the_four_models():
    assert {"full", "mdh", "poe", "offsets"} <= set(model_names())
    with pytest.raises(KeyError, match="known"):
        get_model("nope")


@pytest.mark.parametrize("robot", ROBOTS)
@pytest.mark.parametrize("name", ["full", "mdh", "poe", "offsets"])
def test_jacobian_matches_finite_differences(robot, name):
    chain = _chain(robot)
    model = get_model(name)(chain)
    rng = np.random.default_rng(7)
    x = rng.normal(0, 0.01, model.n_params)  # away from zero: exercises J_r and Hayati terms
    q = rng.uniform(-1.5, 1.5, (12, chain.n_dof))
    pf = rng.normal(0, 0.1, (12, 3))
    _, R, J = model.pin_and_jacobian(x, q, pf)
    h = 1e-6
    for i in range(model.n_params):
        e = np.zeros(model.n_params)
        e[i] = h
        fd = (
            model.pin_and_jacobian(x + e, q, pf, jac=False)[0]
            - model.pin_and_jacobian(x - e, q, pf, jac=False)[0]
        ) / (2 * h)
        scale = 1.0 + np.abs(fd).max()
        assert np.abs(J[:, :, i] - fd).max() < 1e-7 * scale, model.param_names[i]
    # derivative w.r.t. the flange point is the flange rotation
    fd = (
        model.pin_and_jacobian(x, q, pf + [h, 0, 0], jac=False)[0]
        - model.pin_and_jacobian(x, q, pf - [h, 0, 0], jac=False)[0]
    ) / (2 * h)
    assert np.abs(R[:, :, 0] - fd).max() < 1e-8


@pytest.mark.parametrize("robot", ROBOTS)
@pytest.mark.parametrize("name", ["full", "mdh", "poe", "offsets"])
def test_nominal_and_urdf_writeback_are_exact(robot, name):
    urdf = builtin_urdf(robot)
    chain = _chain(robot)
    model = get_model(name)(chain)
    rng = np.random.default_rng(11)
    q = rng.uniform(-2, 2, (50, chain.n_dof))
    pf = np.array([0.01, 0.02, 0.2])
    p0 = model.pin_and_jacobian(model.zero(), q, pf, jac=False)[0]
    assert np.abs(p0 - pin_positions(chain, pf, q)).max() < 1e-13
    x = rng.normal(0, 0.003, model.n_params)
    p = model.pin_and_jacobian(x, q, pf, jac=False)[0]
    assert np.abs(p - pin_positions(model.chain(x), pf, q)).max() < 1e-13
    out = write_calibrated_urdf(urdf, model.origins(x), "flange", pf)
    back = load_chain(out, "base_link", "virtual_pin")
    assert np.abs(fk(back, q)[:, :3, 3] - p).max() < 1e-12


def test_mdh_puts_hayati_on_parallel_axes():
    lr = get_model("mdh")(_chain("lrmate"))
    # LR Mate: J2 parallel to J3 -> joint_3 gets beta instead of d
    assert "joint_3.beta" in lr.param_names and "joint_3.d" not in lr.param_names
    assert "joint_2.d" in lr.param_names
    ur = get_model("mdh")(_chain("ur5e"))
    betas = [n for n in ur.param_names if n.endswith(".beta")]
    assert len(betas) == 2  # UR: J2 || J3 || J4
    # the constant correction E_i is the identity for exactly parallel nominal axes
    assert np.abs(lr.E - np.eye(4)).max() < 1e-12


def test_mdh_refuses_prismatic():
    urdf = """<robot name="p"><link name="base_link"/><link name="a"/><link name="flange"/>
    <joint name="s" type="prismatic"><parent link="base_link"/><child link="a"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="1" effort="1" velocity="1"/></joint>
    <joint name="r" type="revolute"><parent link="a"/><child link="flange"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>"""
    with pytest.raises(BadInput, match="prismatic"):
        get_model("mdh")(load_chain(urdf, "base_link", "flange"))
    # the full model handles it, Jacobian included
    m = get_model("full")(load_chain(urdf, "base_link", "flange"))
    assert m.param_units[m.param_names.index("s.dq0")] == "m"


def test_so3_right_jacobian():
    rng = np.random.default_rng(0)
    for r in (rng.normal(0, 0.5, 3), np.array([1e-8, 0, 0])):
        dr = rng.normal(0, 1e-7, 3)
        lhs = so3_exp(r + dr)
        rhs = so3_exp(r) @ so3_exp(so3_right_jacobian(r) @ dr)
        assert np.abs(lhs - rhs).max() < 1e-13


def test_observability_indices():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(60, 8))
    o = observability(J)
    s = np.linalg.svd(J, compute_uv=False)
    assert o["O2"] == pytest.approx(s[-1] / s[0])
    assert o["O3"] == pytest.approx(s[-1])
    assert o["O4"] == pytest.approx(s[-1] ** 2 / s[0])
    assert o["O1"] == pytest.approx(np.prod(s) ** (1 / 8) / np.sqrt(60))
    assert o["O5"] == pytest.approx(1 / np.sum(1 / s))
    assert o["cond"] == pytest.approx(s[0] / s[-1])
    # nuisance columns are projected out: a column copied into them stops counting
    assert observability(J[:, :7], J[:, 7:])["O3"] <= observability(J[:, :7])["O3"] + 1e-12
    dup = np.column_stack([J[:, :7], J[:, 6]])
    assert observability(dup[:, :7], dup[:, 7:])["O3"] < 1e-10
    assert indices_from_singular_values([1.0, 0.0], 5)["O1"] == 0.0


PRISMATIC = """<robot name="p"><link name="base_link"/><link name="a"/><link name="b"/>
<link name="flange"/>
<joint name="s" type="prismatic"><parent link="base_link"/><child link="a"/>
<origin xyz="0.1 0 0.2" rpy="0 0.2 0"/><axis xyz="0 0 1"/>
<limit lower="0" upper="1" effort="1" velocity="1"/></joint>
<joint name="r1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0.1 0.3"/>
<axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<joint name="r2" type="revolute"><parent link="b"/><child link="flange"/><origin xyz="0.2 0 0"/>
<axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>"""


@pytest.mark.parametrize("name", ["full", "poe", "offsets"])
def test_prismatic_joint_jacobian_and_writeback(name):
    chain = load_chain(PRISMATIC, "base_link", "flange")
    model = get_model(name)(chain)
    rng = np.random.default_rng(5)
    x = rng.normal(0, 0.01, model.n_params)
    q = np.column_stack([rng.uniform(0, 1, 8), rng.uniform(-1, 1, (8, 2))])
    pf = np.array([0.0, 0.05, 0.1])
    p, _, J = model.pin_and_jacobian(x, q, pf)
    h = 1e-6
    for i in range(model.n_params):
        e = np.zeros(model.n_params)
        e[i] = h
        fd = (
            model.pin_and_jacobian(x + e, q, pf, jac=False)[0]
            - model.pin_and_jacobian(x - e, q, pf, jac=False)[0]
        ) / (2 * h)
        assert np.abs(J[:, :, i] - fd).max() < 1e-7, model.param_names[i]
    assert np.abs(p - pin_positions(model.chain(x), pf, q)).max() < 1e-13
