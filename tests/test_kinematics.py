"""Kinematics core against independent references and its own invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from support.robots_dh import IIWA_DH, LRMATE_DH, UR5E_DH, dh_fk, dh_urdf

from pipeline.errors import BadInput
from pipeline.kinematics import fk, fk_frames, jacobian, load_chain, parse_urdf
from pipeline.kinematics.se3 import invert_transform, rotation_angle

ARMS = {"ur5e": UR5E_DH, "lrmate": LRMATE_DH, "iiwa7": IIWA_DH}


def _rot_err(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.max(rotation_angle(np.swapaxes(Ra, -1, -2) @ Rb)))


@pytest.mark.parametrize("arm", sorted(ARMS))
def test_fk_matches_closed_form_dh(arm: str) -> None:
    table = ARMS[arm]
    chain = load_chain(dh_urdf(table), "base_link", "flange")
    assert chain.n_dof == len(table)
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (1000, len(table)))
    T = fk(chain, q)
    T_ref = dh_fk(table, q)
    assert np.max(np.abs(T[:, :3, 3] - T_ref[:, :3, 3])) < 1e-12
    assert _rot_err(T[:, :3, :3], T_ref[:, :3, :3]) < 1e-12


def _yourdfpy_fk(xml: str, names: list[str], q: np.ndarray, tip: str) -> np.ndarray:
    import io

    yourdfpy = pytest.importorskip("yourdfpy")
    robot = yourdfpy.URDF.load(io.StringIO(xml), build_scene_graph=True, load_meshes=False)
    out = np.empty((q.shape[0], 4, 4))
    for i, qi in enumerate(q):
        robot.update_cfg(dict(zip(names, qi, strict=True)))
        out[i] = robot.get_transform(tip, "base_link")
    return out


@pytest.mark.parametrize("arm", ["ur5e", "lrmate"])
def test_fk_matches_yourdfpy_dh_arms(arm: str) -> None:
    xml = dh_urdf(ARMS[arm])
    chain = load_chain(xml, "base_link", "flange")
    q = np.random.default_rng(2).uniform(-3, 3, (1000, chain.n_dof))
    T_ref = _yourdfpy_fk(xml, chain.joint_names, q, "flange")
    T = fk(chain, q)
    assert np.max(np.abs(T[:, :3, 3] - T_ref[:, :3, 3])) < 1e-12
    assert _rot_err(T[:, :3, :3], T_ref[:, :3, :3]) < 1e-12


def test_fk_matches_yourdfpy_on_sample_truth(conformance_truth: dict) -> None:
    """A URDF with general rpy origins and signed axes (the sample's true robot)."""
    xml = conformance_truth["true_urdf_with_pin"]
    chain = load_chain(xml, "base_link", "virtual_pin")
    q = np.random.default_rng(3).uniform(-2, 2, (1000, chain.n_dof))
    T_ref = _yourdfpy_fk(xml, chain.joint_names, q, "virtual_pin")
    T = fk(chain, q)
    assert np.max(np.abs(T[:, :3, 3] - T_ref[:, :3, 3])) < 1e-12
    assert _rot_err(T[:, :3, :3], T_ref[:, :3, :3]) < 1e-12


def test_single_and_batch_agree_and_frames_consistent() -> None:
    chain = load_chain(dh_urdf(LRMATE_DH), "base_link", "flange")
    q = np.random.default_rng(4).uniform(-2, 2, (5, 6))
    T = fk(chain, q)
    for i in range(5):
        np.testing.assert_array_equal(fk(chain, q[i]), T[i])
    T2, frames = fk_frames(chain, q)
    np.testing.assert_allclose(T2, T, atol=1e-15)
    assert frames.shape == (5, 6, 4, 4)
    # joint 1 frame does not depend on q
    np.testing.assert_allclose(frames[:, 0], np.broadcast_to(frames[0, 0], (5, 4, 4)))


def test_prismatic_joint() -> None:
    xml = """<robot name="p"><link name="a"/><link name="b"/><link name="c"/>
    <joint name="slide" type="prismatic"><parent link="a"/><child link="b"/>
      <origin xyz="0 0 1" rpy="0 0 0.5"/><axis xyz="1 0 0"/>
      <limit lower="0" upper="1" effort="1" velocity="1"/></joint>
    <joint name="turn" type="continuous"><parent link="b"/><child link="c"/>
      <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/></joint></robot>"""
    chain = load_chain(xml, "a", "c")
    T = fk(chain, np.array([0.3, 0.0]))
    expected = np.array([0, 0, 1.0]) + Rotation.from_euler("z", 0.5).apply([0.4, 0, 0])
    np.testing.assert_allclose(T[:3, 3], expected, atol=1e-15)
    assert chain.lower[0] == 0.0 and chain.upper[1] == np.inf


@st.composite
def _config(draw: st.DrawFn, n: int) -> np.ndarray:
    return np.array([draw(st.floats(-np.pi, np.pi)) for _ in range(n)])


@settings(max_examples=60, deadline=None)
@given(data=st.data(), arm=st.sampled_from(sorted(ARMS)))
def test_jacobian_matches_central_differences(data: st.DataObject, arm: str) -> None:
    chain = load_chain(dh_urdf(ARMS[arm]), "base_link", "flange")
    q = data.draw(_config(chain.n_dof))
    p_tip = np.array([0.01, -0.02, 0.15])
    J = jacobian(chain, q, p_tip)
    h = 1e-6
    for k in range(chain.n_dof):
        dq = np.zeros(chain.n_dof)
        dq[k] = h
        Tp, Tm = fk(chain, q + dq), fk(chain, q - dq)
        dp = (Tp[:3, :3] @ p_tip + Tp[:3, 3] - Tm[:3, :3] @ p_tip - Tm[:3, 3]) / (2 * h)
        dR = Tp[:3, :3] @ Tm[:3, :3].T
        w = Rotation.from_matrix(dR).as_rotvec() / (2 * h)
        np.testing.assert_allclose(J[:3, k], dp, atol=1e-8)
        np.testing.assert_allclose(J[3:, k], w, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_fk_invariants(data: st.DataObject) -> None:
    """Rotations stay orthonormal; the chain composes: T_base_tip = T_base_j @ T_j_tip."""
    chain = load_chain(dh_urdf(UR5E_DH), "base_link", "flange")
    q = data.draw(_config(6))
    T = fk(chain, q)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-13)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-13)
    _, frames = fk_frames(chain, q)
    # the tail chain from joint 3's frame to the flange, evaluated separately
    head = load_chain(dh_urdf(UR5E_DH), "base_link", "link_2")
    tail = load_chain(dh_urdf(UR5E_DH), "link_2", "flange")
    T_comp = fk(head, q[:2]) @ fk(tail, q[2:])
    np.testing.assert_allclose(T_comp, T, atol=1e-14)
    np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-14)


def test_urdf_errors_are_clear() -> None:
    xml = dh_urdf(LRMATE_DH)
    with pytest.raises(BadInput, match="link 'tool0' not found"):
        load_chain(xml, "base_link", "tool0")
    with pytest.raises(BadInput, match="not below"):
        load_chain(xml, "flange", "base_link")
    with pytest.raises(BadInput, match="does not parse"):
        parse_urdf("<robot><joint></robot>")
    branch = xml.replace(
        "</robot>",
        '<link name="x"/><joint name="j_extra" type="fixed"><parent link="link_3"/>'
        '<child link="link_4"/></joint></robot>',
    )
    with pytest.raises(BadInput, match="two parent joints"):
        load_chain(branch, "base_link", "flange")
    floating = xml.replace('name="joint_3" type="revolute"', 'name="joint_3" type="floating"')
    with pytest.raises(BadInput, match="not supported"):
        load_chain(floating, "base_link", "flange")
