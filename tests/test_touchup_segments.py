"""Step 1 of touch-up extraction: where one touch-up ends and the next begins.

A plan made for another pin (``vtcal plan --pin 0.03,0,0.25`` for the standard
cell's 0.047, 0.002, 0.251) starts touch-ups 30+ mm off: the loop probes its
Jacobian (2 mm shifts), then takes one long first step. That step once started a
new, non-converged "touch-up" with a target of its own, and every later target
label moved up by one (a known distance then named the wrong targets: the run
refused it as implausible).
"""

from __future__ import annotations

import numpy as np

from pipeline.stages.touchups.segments import PROBE_SPAN_M, segments


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = (x, y, z)
    return T


def _touchup(x0: float, yaw: float, probes: bool, first_step_m: float) -> list[np.ndarray]:
    """First capture, the probes (2 mm shifts and back), the first step, then a converging loop."""
    poses = [_pose(x0, 0.0, 0.5, yaw)]
    if probes:
        for d in ((0.002, 0, 0), (0, 0.002, 0), (0, 0, 0.002)):
            poses.append(_pose(x0 + d[0], d[1], 0.5 + d[2], yaw))
    y = first_step_m
    poses.append(_pose(x0, y, 0.5, yaw))
    for k in range(1, 4):  # the loop's shrinking steps
        poses.append(_pose(x0, y + 0.001 / 10**k, 0.5, yaw))
    return poses


def _split(poses: list[np.ndarray]) -> list[int]:
    return [len(s) for s in segments(np.array(poses), np.ones(len(poses), bool),
                                     rot_split_rad=0.01, trans_split_m=0.03)]  # fmt: skip


def test_a_long_first_step_after_the_probes_stays_in_its_touchup() -> None:
    a = _touchup(0.0, 0.0, probes=True, first_step_m=0.035)
    b = _touchup(0.3, 0.4, probes=True, first_step_m=0.034)
    assert _split(a + b) == [len(a), len(b)]


def test_a_long_first_step_after_a_lone_capture_stays_in_its_touchup() -> None:
    a = _touchup(0.0, 0.0, probes=False, first_step_m=0.05)
    assert _split(a) == [len(a)]


def test_a_new_pose_in_the_same_orientation_after_a_servoed_touchup_is_a_new_touchup() -> None:
    # the first touch-up's loop moved 35 mm: beyond its probes, so a further 40 mm
    # translation (same orientation, another target) is a new pose
    a = _touchup(0.0, 0.0, probes=True, first_step_m=0.035)
    b = [_pose(0.04, 0.035, 0.5)] + [_pose(0.04, 0.035 + 1e-4 / 10**k, 0.5) for k in range(3)]
    assert _split(a + b) == [len(a), len(b)]
    assert PROBE_SPAN_M < 0.03


def test_relative_poses_are_relative_pose_pair_by_pair_to_the_bit() -> None:
    """Steps 1-3 take the poses of consecutive captures apart in one stacked call: the same
    angles and translations as one call per pair (dF enters the image Jacobian, so equal
    to the last bit, not to a tolerance), also for an empty list."""
    from pipeline.kinematics.se3 import matrix_from_rpy
    from pipeline.stages.touchups.segments import relative_pose, relative_poses

    rng = np.random.default_rng(11)
    T = np.tile(np.eye(4), (40, 1, 1))
    for k in range(40):
        T[k, :3, :3] = matrix_from_rpy(rng.uniform(-np.pi, np.pi, 3))
        T[k, :3, 3] = rng.uniform(-1.0, 1.0, 3)
    T[5] = T[4]  # a pair at one pose: angle 0
    a, b = np.arange(39), np.arange(1, 40)
    angs, ds = relative_poses(T[a], T[b])
    for k in range(39):
        ang, d = relative_pose(T[a[k]], T[b[k]])
        assert ang == angs[k] and np.array_equal(d, ds[k])
    none = relative_poses(T[:0], T[:0])
    assert none[0].shape == (0,) and none[1].shape == (0, 3)
