"""[robot] change_*: an event on top of the drawn robot, everything else the same."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.sim.cell import build_cell
from pipeline.sim.scenario import scenario_from_dict


def _cell(robot: dict) -> object:
    sc = scenario_from_dict({"robot": {"name": "lrmate", **robot}})
    return build_cell(sc, np.random.default_rng(5))


def test_the_change_moves_that_joint_only() -> None:
    base = _cell({})
    moved = _cell(
        {"change_joint": "joint_3", "change_dq0_rad": 1e-3, "change_dxyz_m": [0.0, 0.0, 1e-4]}
    )
    for name, dev in base.deviations.items():
        got = moved.deviations[name]
        if name == "joint_3":
            assert got["dq0_rad"] - dev["dq0_rad"] == pytest.approx(1e-3, abs=1e-15)
            assert np.subtract(got["dxyz_m"], dev["dxyz_m"]) == pytest.approx([0, 0, 1e-4])
        else:
            assert got == dev
    assert np.array_equal(moved.p_vt_flange, base.p_vt_flange)  # camera, pin: the same
    q = np.array([0.1, 0.3, -0.4, 0.2, -0.6, 0.3])
    from pipeline.kinematics.chain import fk

    assert not np.allclose(fk(base.true, q), fk(moved.true, q), atol=1e-6)


def test_an_unknown_joint_is_said() -> None:
    with pytest.raises(ValueError, match="change_joint 'joint_9'"):
        _cell({"change_joint": "joint_9", "change_dq0_rad": 1e-3})
