"""Accuracy evaluation: registrations recover known motions; workspace poses stay in the box."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_accuracy,
    random_deviations,
    register_points,
    registered_errors,
    solve_pin_ik,
    workspace_poses,
)
from pipeline.kinematics import load_chain
from pipeline.kinematics.se3 import matrix_from_axis_angle
from pipeline.robots import builtin_urdf


def test_registration_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3))
    R = matrix_from_axis_angle(np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9]), 0.7)
    dst = 1.002 * src @ R.T + [0.1, -0.2, 0.3]
    R2, t2, c2 = register_points(src, dst, scale=True)
    assert np.allclose(R2, R) and np.allclose(t2, [0.1, -0.2, 0.3]) and c2 == pytest.approx(1.002)
    assert registered_errors(src, dst, scale=True).max() < 1e-12
    # rigid registration cannot absorb the scale
    assert registered_errors(src, dst, scale=False).max() > 1e-4


def test_pin_accuracy_shape_vs_absolute():
    chain = load_chain(builtin_urdf("lrmate"), "base_link", "flange")
    rng = np.random.default_rng(1)
    q = rng.uniform(-1, 1, (100, 6))
    pin = np.array([0.0, 0.0, 0.2])
    same = pin_accuracy(chain, pin, chain, pin, q)
    assert same["shape_max_m"] < 1e-12 and same["abs_max_m"] < 1e-12
    # a uniformly scaled robot is perfect in shape, not in absolute terms
    scaled = chain.with_origins(
        {
            j.name: np.block(
                [
                    [j.T_parent_joint[:3, :3], 1.001 * j.T_parent_joint[:3, 3:]],
                    [np.zeros((1, 3)), np.ones((1, 1))],
                ]
            )
            for j in chain.joints
        }
    )
    acc = pin_accuracy(scaled, 1.001 * pin, chain, pin, q)
    assert acc["shape_max_m"] < 1e-12
    assert acc["abs_rms_m"] > 1e-4
    assert acc["scale"] == pytest.approx(1 / 1.001)
    dev = perturbed_chain(chain, random_deviations(chain, rng))
    acc = pin_accuracy(chain, pin, dev, pin, q)
    assert 1e-4 < acc["shape_rms_m"] <= acc["abs_rms_m"] < 1e-2


def test_workspace_poses_in_the_box():
    rng = np.random.default_rng(2)
    qt = rng.uniform(-0.5, 0.7, (30, 6))
    qw = workspace_poses(qt, 500, np.random.default_rng(3))
    assert qw.shape == (500, 6)
    assert np.all(qw >= qt.min(axis=0)) and np.all(qw <= qt.max(axis=0))
    assert np.all(np.ptp(qw, axis=0) > 0.9 * np.ptp(qt, axis=0))


def test_pin_ik_puts_the_pin_on_target():
    chain = load_chain(builtin_urdf("iiwa7"), "base_link", "flange")
    rng = np.random.default_rng(4)
    pin = np.array([0.01, 0.0, 0.2])
    seeds = rng.uniform(-0.8, 0.8, (20, 7))
    from pipeline.accuracy.evaluate import pin_positions

    goal = pin_positions(chain, pin, seeds + rng.normal(0, 0.1, seeds.shape))
    q, ok = solve_pin_ik(chain, pin, goal, seeds)
    assert ok.mean() > 0.8
    assert np.abs(pin_positions(chain, pin, q[ok]) - goal[ok]).max() < 1e-12
