"""Calibrated URDF writer: FK survives the round trip (vtcal reader and yourdfpy), pin lands where put."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from pipeline.accuracy.evaluate import pin_positions
from pipeline.errors import BadInput
from pipeline.kinematics import fk, load_chain
from pipeline.kinematics.se3 import matrix_from_axis_angle, transform_from
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.robots import builtin_urdf

COMMENTED = """<?xml version="1.0"?>
<!-- a comment that must survive -->
<robot name="two">
  <link name="base_link"><visual><geometry><box size="1 2 3"/></geometry></visual></link>
  <link name="l1"/><link name="flange"/><link name="camera"/>
  <joint name="j1" type="revolute"><parent link="base_link"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="flange"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="cam" type="fixed"><parent link="flange"/><child link="camera"/>
    <origin xyz="0.1 0 0" rpy="0 0 0"/></joint>
</robot>
"""


def _random_origins(chain, rng):
    out = {}
    for j in chain.actuated:
        w = rng.normal(size=3)
        R = matrix_from_axis_angle(w / np.linalg.norm(w), rng.uniform(0, np.pi))
        out[j.name] = j.T_parent_joint @ transform_from(R, rng.normal(0, 0.05, 3))
    return out


@pytest.mark.parametrize("robot", ["lrmate", "iiwa7"])
def test_roundtrip_fk_and_pin(robot):
    urdf = builtin_urdf(robot)
    chain = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(3)
    origins = _random_origins(chain, rng)
    pin = np.array([0.012, -0.03, 0.21])
    out = write_calibrated_urdf(urdf, origins, "flange", pin)
    want = chain.with_origins(origins)
    q = rng.uniform(-2, 2, (200, chain.n_dof))
    back = load_chain(out, "base_link", "flange")
    assert np.abs(fk(back, q) - fk(want, q)).max() < 1e-12
    # the virtual pin: a fixed joint from the flange
    to_pin = load_chain(out, "base_link", "virtual_pin")
    p_true = pin_positions(want, pin, q)
    assert np.abs(fk(to_pin, q)[:, :3, 3] - p_true).max() < 1e-12

    yourdfpy = pytest.importorskip("yourdfpy")
    import io

    model = yourdfpy.URDF.load(io.StringIO(out), build_scene_graph=True, load_meshes=False)
    for qi in q[:20]:
        model.update_cfg(dict(zip(chain.joint_names, qi, strict=True)))
        T_flange = model.get_transform("flange", "base_link")
        T_pin = model.get_transform("virtual_pin", "base_link")
        assert np.abs(T_flange - fk(want, qi)).max() < 1e-12
        assert np.abs(T_pin[:3, 3] - pin_positions(want, pin, qi[None])[0]).max() < 1e-12


def test_keeps_everything_else_and_rewrites_pin():
    chain = load_chain(COMMENTED, "base_link", "flange")
    origins = _random_origins(chain, np.random.default_rng(0))
    out = write_calibrated_urdf(COMMENTED, origins, "flange", [0, 0, 0.2])
    assert "a comment that must survive" in out
    root = ET.fromstring(out)
    assert root.find("link/visual/geometry/box").get("size") == "1 2 3"
    cam = [j for j in root.findall("joint") if j.get("name") == "cam"][0]
    assert cam.find("origin").get("xyz") == "0.1 0 0"
    j1 = [j for j in root.findall("joint") if j.get("name") == "j1"][0]
    assert j1.find("limit").get("lower") == "-3"
    # j2 had no <origin>: one was added
    j2 = [j for j in root.findall("joint") if j.get("name") == "j2"][0]
    assert j2.find("origin") is not None
    # writing again replaces the pin instead of adding a second one
    again = write_calibrated_urdf(out, {}, "flange", [0.1, 0.2, 0.3])
    r2 = ET.fromstring(again)
    assert len([j for j in r2.findall("joint") if j.get("name") == "virtual_pin_joint"]) == 1
    assert len([link for link in r2.findall("link") if link.get("name") == "virtual_pin"]) == 1
    tip = load_chain(again, "base_link", "virtual_pin")
    assert np.allclose(
        fk(tip, np.zeros(2))[:3, 3],
        fk(chain.with_origins(origins), np.zeros(2))[:3, 3]
        + fk(chain.with_origins(origins), np.zeros(2))[:3, :3] @ [0.1, 0.2, 0.3],
    )


def test_bad_names_are_one_line_errors():
    with pytest.raises(BadInput, match="no joint"):
        write_calibrated_urdf(COMMENTED, {"nope": np.eye(4)}, "flange", [0, 0, 0])
    with pytest.raises(BadInput, match="no link"):
        write_calibrated_urdf(COMMENTED, {}, "nolink", [0, 0, 0])
