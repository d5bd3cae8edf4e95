"""The error models' batched helpers equal their one-at-a-time definitions (issue 19).

The kinematics of every model evaluate all joints in one pass
(:func:`joint_motions`, :func:`so3_exp_many`, :func:`so3_right_jacobian_many`,
a broadcasting :func:`point_motion`); these tests hold them to the per-joint
formulas they replaced, including the small-angle branches.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.kinematics import load_chain
from pipeline.models import get_model
from pipeline.models.base import (
    joint_motions,
    motion,
    point_motion,
    so3_exp,
    so3_exp_many,
    so3_right_jacobian,
    so3_right_jacobian_many,
)
from pipeline.robots import builtin_urdf


def _vectors(rng: np.random.Generator) -> np.ndarray:
    """Rotation vectors across both branches: zero, below and above each cut, large."""
    unit = rng.normal(size=(7, 3))
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    sizes = np.array([0.0, 1e-13, 5e-12, 5e-7, 2e-6, 0.3, 3.0])
    return unit * sizes[:, None]


def test_so3_exp_many_equals_one_at_a_time():
    r = _vectors(np.random.default_rng(0))
    many = so3_exp_many(r)
    for k in range(len(r)):
        assert np.abs(many[k] - so3_exp(r[k])).max() < 1e-15


def test_so3_right_jacobian_many_equals_one_at_a_time():
    r = _vectors(np.random.default_rng(1))
    many = so3_right_jacobian_many(r)
    for k in range(len(r)):
        assert np.abs(many[k] - so3_right_jacobian(r[k])).max() < 1e-15


def test_joint_motions_equal_motion_per_joint():
    rng = np.random.default_rng(2)
    axis = rng.normal(size=(5, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    prismatic = np.array([False, True, False, False, True])
    q = rng.uniform(-3, 3, (11, 5))
    M = joint_motions(axis, prismatic, q)
    assert M.shape == (11, 5, 4, 4)
    for k in range(5):
        assert np.abs(M[:, k] - motion(axis[k], bool(prismatic[k]), q[:, k])).max() < 1e-15


def test_point_motion_broadcasts_over_leading_axes():
    rng = np.random.default_rng(3)
    T = np.tile(np.eye(4), (4, 9, 1, 1))
    T[..., :3, :3] = so3_exp_many(rng.normal(size=(36, 3))).reshape(4, 9, 3, 3)
    T[..., :3, 3] = rng.normal(size=(4, 9, 3))
    tw = rng.normal(size=(4, 1, 6, 2))
    p = rng.normal(size=(9, 3))
    out = point_motion(T, tw, p)
    assert out.shape == (4, 9, 3, 2)
    for k in range(4):
        one = point_motion(T[k], tw[k, 0], p)
        assert np.abs(out[k] - one).max() < 1e-15
        # equation (1) written out for one pose and twist
        R, o = T[k, 5, :3, :3], T[k, 5, :3, 3]
        v, w = tw[k, 0, :3, 1], tw[k, 0, 3:, 1]
        assert np.abs(out[k, 5, :, 1] - (R @ v + np.cross(R @ w, p[5] - o))).max() < 1e-14


@pytest.mark.parametrize("robot", ["lrmate", "iiwa7"])
def test_elastic_torque_is_recomputed_for_new_joint_vectors(robot):
    """The elastic model reuses the gravity torque of the last ``q`` only while ``q`` is equal."""
    chain = load_chain(builtin_urdf(robot), "base_link", "flange")
    model = get_model("elastic")(chain)
    rng = np.random.default_rng(4)
    x = rng.normal(0, 1e-3, model.n_params)
    x[model.n_kin :] = 1e-4
    pf = np.array([0.01, 0.02, 0.15])
    q1 = rng.uniform(-1.5, 1.5, (6, chain.n_dof))
    q2 = q1.copy()
    q2[3, 1] += 0.4
    first = model.pin_and_jacobian(x, q1, pf)
    second = model.pin_and_jacobian(x, q2, pf)  # same shape, one value changed
    fresh = get_model("elastic")(chain).pin_and_jacobian(x, q2, pf)
    for a, b in zip(second, fresh, strict=True):
        assert np.array_equal(a, b)
    assert not np.array_equal(first[0][3], second[0][3])
    q2[3, 1] -= 0.4  # the caller mutates its array in place: still not served stale
    again = model.pin_and_jacobian(x, q2, pf)
    for a, b in zip(again, first, strict=True):
        assert np.array_equal(a, b)
