"""The touch-up loop (pipeline.live.loop) on an analytic fake cell (tests/support/fake_cell.py).

Known truth: the fake's flange position at which the disc is seen at the goal,
and its analytic image Jacobian. Every test can fail: convergence to that
position, the probed Jacobian against the analytic one, step clipping, the
give-up rules, stillness, and the Broyden update against a wrong start.
"""

from __future__ import annotations

import numpy as np
import pytest
from support.fake_cell import FakeCell

from pipeline.live.loop import (
    CaptureInfo,
    Goal,
    LoopConfig,
    broyden_update,
    estimate_jacobian,
    touch_up,
)
from pipeline.live.protocols import Frame
from pipeline.measurement.image_jacobian import servo_step

GOAL = Goal(u0=319.5, v0=239.5, s0=80.0, threshold_px=0.5, threshold_size_px=0.5, polarity="x")


def _cell(offset_m: tuple[float, float, float] = (0.003, -0.002, 0.004), **kw: object) -> FakeCell:
    cell = FakeCell(**kw)  # type: ignore[arg-type]
    cell.p = cell.flange_for(GOAL.u0, GOAL.v0, GOAL.s0) + np.asarray(offset_m)
    return cell


def _run(cell: FakeCell, cfg: LoopConfig, J: np.ndarray | None = None):  # type: ignore[no-untyped-def]
    got: list[tuple[Frame, CaptureInfo]] = []

    def on_capture(frame: Frame, info: CaptureInfo) -> None:
        got.append((frame, info))

    if J is None:
        J = estimate_jacobian(cell, cell, cell.detect, on_capture, GOAL, cfg, 0)
    res = touch_up(cell, cell, cell.detect, on_capture, GOAL, cfg, J, 0)
    return res, got


def test_converges_to_the_goal_pose_with_extra_captures() -> None:
    cell = _cell(noise_px=0.02, seed=1)
    res, got = _run(cell, LoopConfig())
    assert res.converged and not res.lost and res.reason == "converged"
    assert res.final_error_px is not None
    assert abs(res.final_error_px[0]) <= 0.5 and abs(res.final_error_px[1]) <= 0.5
    assert abs(res.final_error_px[2]) <= 0.5
    # the pose the loop stopped at sees the disc at the goal (truth, noise-free)
    u, v, s = cell.uvs()
    assert abs(u - GOAL.u0) < 0.6 and abs(v - GOAL.v0) < 0.6 and abs(s - GOAL.s0) < 0.6
    np.testing.assert_allclose(res.joints.positions, cell.p)
    kinds = [i.kind for _, i in got]
    assert kinds[:7] == ["probe"] * 7
    assert kinds[-2:] == ["extra", "extra"] and kinds.count("loop") == res.iterations
    assert [i.kind for i in res.captures] == kinds[7:]
    assert all(i.still for _, i in got)
    assert res.iterations < 6  # gain 0.9 from a few mm: a handful of steps


def test_probed_jacobian_matches_the_analytic_one_and_returns_to_base() -> None:
    cell = _cell(A=np.array([[1.01, 0.02, 0.0], [-0.02, 0.99, 0.01], [0.0, 0.0, 1.0]]))
    p0 = cell.p.copy()
    J_true = cell.jacobian()
    J = estimate_jacobian(cell, cell, cell.detect, lambda f, i: None, GOAL, LoopConfig(), 0)
    assert J is not None
    # central differences: O(h^2) truncation, h = 2 mm at a 0.1 m stand-off
    np.testing.assert_allclose(J, J_true, rtol=2e-3, atol=2e-3 * np.abs(J_true).max())
    np.testing.assert_allclose(cell.p, p0, atol=1e-15)
    assert len(cell.moves) == 7  # six shifts and the way back, each a pure translation
    np.testing.assert_allclose(np.sum(cell.moves, axis=0), 0.0, atol=1e-15)


def test_probing_fails_when_the_target_is_hidden() -> None:
    cell = _cell(hidden=True)
    res, got = _run(cell, LoopConfig())
    assert res.reason == "no_jacobian" and res.lost and not res.converged
    assert res.iterations == 0 and res.captures == [] and len(got) == 7


def test_step_is_clipped_along_its_own_direction() -> None:
    J = np.diag([8000.0, 8000.0, -0.12])
    e = np.array([300.0, -200.0, 0.0])
    dp = servo_step(J, e, 0.9, 0.01)
    full = -0.9 * np.linalg.solve(J, e)
    assert np.linalg.norm(full) > 0.01
    assert np.linalg.norm(dp) == pytest.approx(0.01)
    np.testing.assert_allclose(dp / np.linalg.norm(dp), full / np.linalg.norm(full))
    # in the loop: a 25 mm start, steps of at most 4 mm
    cell = _cell(offset_m=(0.015, 0.0, 0.02))
    J0 = cell.jacobian()
    res, _ = _run(cell, LoopConfig(max_step_m=0.004, max_iterations=30), J0)
    assert res.converged
    norms = [float(np.linalg.norm(m)) for m in cell.moves]
    assert max(norms) == pytest.approx(0.004) and sum(n > 0.0039 for n in norms) >= 5


def test_gives_up_when_the_target_is_lost() -> None:
    cell = _cell()
    J = cell.jacobian()
    cell.hidden = True
    res, got = _run(cell, LoopConfig(), J)
    assert res.reason == "lost_target" and res.lost and not res.converged
    assert res.iterations == 1 and len(got) == 1 and res.final_error_px is None


def test_gives_up_at_the_border() -> None:
    cell = _cell()
    J = cell.jacobian()
    # the disc's centre 20 px from the left edge: its 80 px circle is cut
    cell.p = cell.flange_for(20.0, GOAL.v0, GOAL.s0)
    res, _ = _run(cell, LoopConfig(), J)
    assert res.reason == "border" and res.lost and res.iterations == 1
    assert res.final_error_px is not None and res.final_error_px[0] == pytest.approx(-299.5)


def test_gives_up_at_the_iteration_limit() -> None:
    cell = _cell()
    res, got = _run(cell, LoopConfig(gain=0.1, max_iterations=5), cell.jacobian())
    assert res.reason == "iteration_limit" and not res.converged and not res.lost
    assert res.iterations == 5 and [i.kind for _, i in got] == ["loop"] * 5
    assert len(cell.moves) == 4  # no step after the last capture


def test_waits_for_stillness_and_rejects_a_capture_while_moving() -> None:
    cell = _cell(busy_s=0.4)
    J = cell.jacobian()
    cell.move_joints(cell.p, 0.1)  # just arrived: moving for 0.4 s more
    t0 = cell.t_ns
    cell.p = cell.flange_for(GOAL.u0 + 0.1, GOAL.v0, GOAL.s0)  # already at the goal
    res, got = _run(cell, LoopConfig(still_poll_s=0.05), J)
    first = got[0][1]
    assert first.still and first.stamp_ns >= t0 + 0.4e9
    assert res.converged and res.iterations == 1
    # a controller that says "still" too early: the capture is flagged, not converged on
    cell = _cell(busy_s=0.4)
    cell.p = cell.flange_for(GOAL.u0 + 0.1, GOAL.v0, GOAL.s0)
    cell.move_joints(cell.p, 0.1)
    cell.lie_still = 1
    res, got = _run(cell, LoopConfig(still_poll_s=0.05), J)
    assert not got[0][1].still and got[1][1].still
    assert res.converged and res.iterations == 2


def test_still_timeout_captures_anyway_flagged() -> None:
    cell = _cell(busy_s=100.0)
    J = cell.jacobian()
    cell.move_joints(cell.p, 0.1)
    res, got = _run(cell, LoopConfig(still_timeout_s=0.2, max_iterations=3), J)
    assert not any(i.still for _, i in got) and not res.converged
    assert res.reason == "iteration_limit"


def test_broyden_update_satisfies_the_secant_condition() -> None:
    rng = np.random.default_rng(3)
    J = rng.normal(size=(3, 3))
    dp = rng.normal(size=3)
    de = rng.normal(size=3)
    Jn = broyden_update(J, dp, de)
    np.testing.assert_allclose(Jn @ dp, de, atol=1e-12)
    w = np.cross(dp, rng.normal(size=3))  # orthogonal to dp: unchanged
    np.testing.assert_allclose(Jn @ w, J @ w, atol=1e-12)


def test_jacobian_update_rescues_a_wrong_start() -> None:
    """A Jacobian whose image axes are turned by 70 degrees: the fixed-J loop spirals
    and does not converge in 12 captures; the updated one converges and ends nearer
    the true Jacobian along the directions it moved."""
    R = np.eye(3)
    c, s = np.cos(np.deg2rad(70.0)), np.sin(np.deg2rad(70.0))
    R[:2, :2] = [[c, -s], [s, c]]
    cell = _cell(offset_m=(0.004, 0.003, 0.002), noise_px=0.02, seed=5)
    J_true = cell.jacobian()
    J_wrong = R @ J_true
    p0 = cell.p.copy()
    fixed, _ = _run(cell, LoopConfig(update_jacobian=False), J_wrong)
    cell.p = p0.copy()
    cell.moves.clear()
    upd, _ = _run(cell, LoopConfig(update_jacobian=True), J_wrong)
    assert not fixed.converged
    assert upd.converged and upd.iterations < 12
    assert upd.jacobian is not None
    err0 = np.linalg.norm((J_wrong - J_true) @ np.array(cell.moves).T)
    err1 = np.linalg.norm((upd.jacobian - J_true) @ np.array(cell.moves).T)
    assert err1 < 0.5 * err0


def test_the_probe_is_the_one_estimator_and_gives_central_differences() -> None:
    """(J1) on the live probe's six pairs is each column's central difference, whatever
    the curvature (the pairs are symmetric), and the servo step is the core's residual
    correction times the gain (J2)."""
    from pipeline.live.loop import jacobian_from_probes, probe_shifts
    from pipeline.measurement.image import residual_correction

    rng = np.random.default_rng(4)
    h = 0.002
    A = rng.normal(size=(3, 3)) * [[4000.0], [4000.0], [0.1]]
    m0 = np.array([320.0, 240.0, 1 / 80.0])
    # a curved image map: m(d) = m0 + A d + quadratic terms
    meas = [
        m0 + A @ d + 50.0 * np.array([d @ d, d[0] * d[1], 1e-4 * d[2] ** 2])
        for d in probe_shifts(h)
    ]
    central = np.stack([(meas[1 + 2 * k] - meas[2 + 2 * k]) / (2 * h) for k in range(3)], axis=1)
    J = jacobian_from_probes(meas, h)
    assert J is not None
    np.testing.assert_allclose(J, central, rtol=1e-9, atol=1e-12)
    e = np.array([3.0, -2.0, 1e-4])
    np.testing.assert_allclose(servo_step(J, e, 0.7, 1.0), 0.7 * residual_correction(J, e))
    assert not np.any(servo_step(np.zeros((3, 3)), e, 0.7, 1.0))  # singular: no step
