"""The elastic model's mass models: elastic_mid, elastic_inertial, the inertial reader, payloads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.accuracy.evaluate import synthetic_touchups
from pipeline.errors import BadInput
from pipeline.kinematics import load_chain
from pipeline.kinematics.urdf import parse_urdf
from pipeline.models import get_model, make_model
from pipeline.models.elastic import G_BASE
from pipeline.robots import builtin_urdf
from pipeline.stages.identify.stage import IdentifyConfig, identify

REPO = Path(__file__).resolve().parent.parent
PANDA_INERTIAL = REPO / "datasets" / "real" / "mukca" / "nominal_panda_inertial.urdf"
PANDA = REPO / "datasets" / "real" / "mukca" / "nominal_panda.urdf"
PIN = np.array([0.0167, -0.0101, 0.2524])
G = float(np.linalg.norm(G_BASE))


def _panda(inertial: bool = True):
    path = PANDA_INERTIAL if inertial else PANDA
    return load_chain(path.read_text(), "panda_link0", "panda_hand_tcp")


def _planar_urdf(inertials: bool) -> str:
    """Two revolute joints about y (a vertical plane), links 0.5 m and 0.3 m along x.

    link1: 2 kg at (0.25, 0, 0); link2: 1 kg at (0.1, 0, 0.05) plus a finger hanging
    off it (prismatic, off the chain) of 0.5 kg at (0.3, 0, 0) in link2's frame.
    """

    def inertial(m, xyz):
        if not inertials:
            return ""
        return f'<inertial><origin xyz="{xyz}" rpy="0 0 0.3"/><mass value="{m}"/></inertial>'

    return f"""<robot name="planar">
  <link name="base"/>
  <link name="link1">{inertial(2.0, "0.25 0 0")}</link>
  <link name="link2">{inertial(1.0, "0.1 0 0.05")}</link>
  <link name="finger">{inertial(0.5, "0 0 0")}</link>
  <link name="flange"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="link1"/>
    <origin xyz="0 0 0.2"/><axis xyz="0 1 0"/><limit lower="-3" upper="3"/></joint>
  <joint name="j2" type="revolute"><parent link="link1"/><child link="link2"/>
    <origin xyz="0.5 0 0"/><axis xyz="0 1 0"/><limit lower="-3" upper="3"/></joint>
  <joint name="tip" type="fixed"><parent link="link2"/><child link="flange"/>
    <origin xyz="0.3 0 0"/></joint>
  <joint name="grip" type="prismatic"><parent link="link2"/><child link="finger"/>
    <origin xyz="0.3 0 0"/><axis xyz="0 0 1"/><limit lower="0" upper="0.04"/></joint>
</robot>"""


def _planar(inertials: bool = True):
    return load_chain(_planar_urdf(inertials), "base", "flange")


def _fd_check(m, x, q, pf):
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


@pytest.mark.parametrize(
    ("name", "chain"),
    [
        ("elastic_mid", "lrmate"),
        ("elastic_mid", "panda"),
        ("elastic_inertial", "panda"),
        ("elastic_inertial", "planar"),
    ],
)
def test_jacobian_matches_finite_differences(name, chain):
    ch = {
        "lrmate": lambda: load_chain(builtin_urdf("lrmate"), "base_link", "flange"),
        "panda": _panda,
        "planar": _planar,
    }[chain]()
    m = make_model(name, ch)
    rng = np.random.default_rng(3)
    x = rng.normal(0, 0.01, m.n_params)
    x[m.n_kin :] = rng.normal(0, 1e-4, m.n_params - m.n_kin)
    q = rng.uniform(-1.5, 1.5, (8, ch.n_dof))
    pf = rng.normal(0, 0.1, (8, 3))
    _fd_check(m, x, q, pf)
    m.set_payload(1.5, (0.01, -0.02, 0.05))  # a payload changes tau, not the chain rule (E4)
    _fd_check(m, x, q, pf)


def test_inertial_reader_on_a_small_urdf():
    robot = parse_urdf(_planar_urdf(True))
    assert robot.inertials["link1"].mass == 2.0
    assert np.allclose(robot.inertials["link2"].com, [0.1, 0, 0.05])  # rpy ignored
    assert "base" not in robot.inertials and "flange" not in robot.inertials
    chain = _planar()
    # link2 carries the finger (off the chain, at zero stroke): 1.5 kg, mass-weighted centre
    c2 = chain.inertials["link2"]
    assert c2.mass == pytest.approx(1.5)
    assert np.allclose(c2.com, (1.0 * np.array([0.1, 0, 0.05]) + 0.5 * np.array([0.3, 0, 0])) / 1.5)
    assert set(chain.inertials) == {"link1", "link2"}
    # the chain keeps them through its copies
    assert chain.with_origins({}).inertials is chain.inertials
    assert chain.with_tip(np.eye(4)).inertials is chain.inertials
    # a URDF without inertials: nothing, the kinematics unchanged
    assert parse_urdf(_planar_urdf(False)).inertials == {}
    assert _planar(False).inertials == {}
    with pytest.raises(BadInput, match="mass"):
        parse_urdf(_planar_urdf(True).replace('<mass value="2.0"/>', '<mass value="-2"/>'))


def test_inertial_torque_by_hand():
    """Planar arm at q: tau_j = g * sum over the masses beyond j of m * horizontal lever."""
    m = make_model("elastic_inertial", _planar())
    q = np.array([[0.0, 0.0], [0.3, -0.5]])
    for i, (t1, t2) in enumerate(q):
        # Rot(y, t) takes x to (cos t, 0, -sin t); z to (sin t, 0, cos t)
        x1 = 0.25 * np.cos(t1)  # link1's mass, from joint 1
        c2 = (np.array([0.1, 0, 0.05]) + 0.5 * np.array([0.3, 0, 0])) / 1.5
        x2 = c2[0] * np.cos(t1 + t2) + c2[2] * np.sin(t1 + t2)  # from joint 2
        tau2 = 1.5 * G * x2
        tau1 = 2.0 * G * x1 + 1.5 * G * (0.5 * np.cos(t1) + x2)
        # tau = a . (r x m g), a = y, g = -z: a . (r x (0, 0, -m g)) = m g r_x
        assert m.torque(q[i]) == pytest.approx(np.array([[tau1, tau2]]), abs=1e-12)


def test_payload_changes_the_deflection_by_its_torque():
    """2-joint planar chain: a payload of 2 kg at (0.1, 0, 0) in the flange frame."""
    for name in ("elastic", "elastic_mid", "elastic_inertial"):
        m = make_model(name, _planar())
        x = np.zeros(m.n_params)
        c = np.array([3e-4, 5e-4])
        x[m.n_kin :] = c
        q = np.array([[0.0, 0.0], [0.3, -0.5], [-0.7, 1.1]])
        lever2 = (0.3 + 0.1) * np.cos(q[:, 0] + q[:, 1])  # flange + 0.1 m along its x
        lever1 = 0.5 * np.cos(q[:, 0]) + lever2
        extra = np.stack([2.0 * G * lever1, 2.0 * G * lever2], axis=1)  # N m, hand computed
        base = m.deflection(x, q)
        m.set_payload(2.0, (0.1, 0.0, 0.0))
        assert m.deflection(x, q) - base == pytest.approx(c * extra, abs=1e-14)
        assert m.mass_model()["payload"] == {"mass_kg": 2.0, "com_flange_m": [0.1, 0.0, 0.0]}
        # one mass per row, at the set centre of mass
        per_row = m.deflection(x, q, payload_kg=np.array([0.0, 2.0, 4.0]))
        want = base + c * extra * np.array([0.0, 1.0, 2.0])[:, None]
        assert per_row == pytest.approx(want, abs=1e-14)
        # predictions follow: the pin of predict() with a payload is the map at q + deflection
        p_pay = m.predict(x, q, PIN, payload_kg=np.array([0.0, 2.0, 4.0]))
        full = get_model("full")(m.nominal)
        assert np.allclose(p_pay, full.pin_and_jacobian(x[: m.n_kin], q + want, PIN, jac=False)[0])
        m.set_payload(0.0)
        assert np.array_equal(m.deflection(x, q), base)
        with pytest.raises(ValueError, match="payload"):
            m.set_payload(-1.0)


def test_no_inertials_no_inertial_model():
    for chain in (_panda(inertial=False), _planar(False)):
        with pytest.raises(BadInput, match="no <inertial>"):
            make_model("elastic_inertial", chain)
    with pytest.raises(BadInput, match="no <inertial>"):
        make_model("elastic_inertial", load_chain(builtin_urdf("ur5e"), "base_link", "flange"))
    # the lumped candidates need none
    for name in ("elastic", "elastic_mid"):
        assert make_model(name, _panda(inertial=False)).n_params == 7 * 7 + 7


def test_mass_models_are_json_and_say_what_they_are():
    chain = _panda()
    got = {
        n: make_model(n, chain).mass_model() for n in ("elastic", "elastic_mid", "elastic_inertial")
    }
    for d in got.values():
        json.dumps(d)
        assert d["gravity_m_s2"] == [0.0, 0.0, -9.81] and d["payload"]["mass_kg"] == 0.0
    assert got["elastic"]["kind"] == "lumped_joint_origins" and not got["elastic"]["physical"]
    assert got["elastic"]["total_kg"] == 8.0  # 7 joints + tip
    assert (
        got["elastic_mid"]["kind"] == "lumped_link_midpoints"
        and got["elastic_mid"]["total_kg"] == 7.0
    )
    ine = got["elastic_inertial"]
    assert ine["kind"] == "urdf_inertials" and ine["physical"]
    # Gaz et al. 2019's links 1-7 plus the hand with its fingers (0.73 + 2 x 0.015)
    assert ine["total_kg"] == pytest.approx(
        4.970684 + 0.646926 + 3.228604 + 3.587895 + 1.225946 + 1.666555 + 0.735522 + 0.76
    )
    # the hand (after the fixed panda_joint8 and panda_hand_joint) rides on joint 7
    hand = next(d for d in ine["masses"] if d["label"] == "panda_hand")
    assert hand["body"] == "panda_joint7" and hand["position_m"][2] == pytest.approx(
        0.107 + 0.0311, abs=1e-3
    )


@pytest.mark.parametrize("name", ["elastic_inertial", "elastic_mid"])
def test_recovers_a_simulated_compliance(name):
    """Seeded: the Panda with known compliances on top of full-model errors; identify recovers them."""
    nominal = _panda()
    m = make_model(name, nominal)
    rng = np.random.default_rng(21)
    scale = 1e-4 if name == "elastic_inertial" else 3e-4  # rad/(N m): ~1 mrad at ~10 N m
    c_true = scale * np.array([0.0, 1.0, 0.8, 1.2, 0.6, 0.9, 0.5])
    x_true = np.concatenate([rng.normal(0, 4e-4, m.n_kin), c_true])
    centre = np.array([0.0, 0.3, 0.0, -2.0, 0.0, 2.3, 0.8])
    table, targets = synthetic_touchups(m.chain(x_true), PIN, 3, 16, rng, q_centre=centre)
    names = nominal.joint_names
    q_true = table[names].to_numpy()
    q = q_true.copy()
    for _ in range(50):  # the encoder reads q with q + c tau(q) = q' (fixed point of (E1))
        q = q_true - m.deflection(x_true, q)
    table[names] = q
    d = float(np.linalg.norm(targets[0] - targets[1]))
    res = identify(
        table,
        PANDA_INERTIAL.read_text(),
        "panda_link0",
        "panda_hand_tcp",
        IdentifyConfig(model=name, distances=[(0, 1, d)]),
    )
    ident = res.parameters.set_index("name")
    found = 0
    for j, jn in enumerate(names):
        row = ident.loc[f"{jn}.compliance"]
        if row["identifiable"]:
            found += 1
            assert row["value"] == pytest.approx(c_true[j], rel=1e-3, abs=1e-9), jn
    assert found >= 4
    assert not ident.loc["panda_joint1.compliance", "identifiable"]  # vertical: no torque
