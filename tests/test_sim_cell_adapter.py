"""The simulated cell behind the measurement protocols (pipeline.sim.cell_adapter).

Against the simulator's own truth: a flange move moves the true flange by the
commanded translation up to the nominal/true kinematic gap, stillness follows
the settle time, the camera renders the target in view, and the shared loop
with vtcal's own detector touches up a standalone cell (no recording) so that
the true virtual pin lands on the target.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.kinematics.chain import fk
from pipeline.live.detector import vtcal_detector
from pipeline.live.loop import estimate_jacobian, touch_up
from pipeline.live.protocols import Camera, Robot
from pipeline.sim.cell_adapter import SimCell
from pipeline.sim.scenario import load_scenario

SCEN = Path(__file__).resolve().parent.parent / "datasets" / "scenarios"


@pytest.fixture(scope="module")
def cell() -> SimCell:
    return SimCell.from_scenario(load_scenario(SCEN / "small.toml"), 11)


def test_protocols_and_standalone_state(cell: SimCell) -> None:
    assert isinstance(cell.robot, Robot) and isinstance(cell.camera, Camera)
    assert cell.robot.joint_names == cell.sess.cell.nominal.joint_names
    assert "<robot" in cell.nominal_urdf and cell.metadata["polarity"] == cell.goal.polarity
    assert len(cell.plan) == 6 and sorted(cell.labels) == [0, 1, 2]
    assert cell.sess.rec.sequence == 0  # standalone: nothing recorded


def test_moves_stillness_and_flange_translation(cell: SimCell) -> None:
    robot = cell.robot
    tid, q = cell.plan[0]
    robot.move_joints(q, 1.0)
    assert robot.is_still()
    np.testing.assert_allclose(robot.read_joints().positions, q)
    true = cell.sess.cell.true
    T0 = fk(true, robot.read_joints().positions)
    t0 = robot.read_joints().stamp_ns
    dp = np.array([0.003, -0.002, 0.001])
    robot.move_flange(dp)
    assert robot.is_still() and robot.read_joints().stamp_ns > t0
    T1 = fk(true, robot.read_joints().positions)
    moved = T0[:3, :3].T @ (T1[:3, 3] - T0[:3, 3])  # in the flange frame
    # the controller uses the nominal chain: the true flange moves by dp up to the
    # deviations' effect (well under 1 % of a few mm), and does not turn
    np.testing.assert_allclose(moved, dp, atol=2e-5)
    assert np.linalg.norm(T1[:3, :3] - T0[:3, :3]) < 1e-4
    # a move is not still until it ended and settled
    robot.arm.start_move(cell.plan[1][1], 1.0)
    assert not robot.is_still()
    robot.wait(1.0 + cell.sess.sc.timing.settle_s)
    assert robot.is_still()


def test_loop_with_vtcal_detector_puts_the_pin_on_the_target(cell: SimCell) -> None:
    tid, q = cell.plan[2]
    cell.robot.move_joints(q, 1.0)
    cell.camera.target = None  # standalone: the target in view
    assert cell.camera.target_in_view().id == tid
    detect = vtcal_detector(cell.goal.polarity, size_px=cell.goal.s0)
    cfg = cell.loop_config()
    frames = []
    J = estimate_jacobian(
        cell.robot, cell.camera, detect, lambda f, i: frames.append(f), cell.goal, cfg, 0
    )
    assert J is not None and len(frames) == 7
    res = touch_up(cell.robot, cell.camera, detect, lambda f, i: None, cell.goal, cfg, J, 0)
    assert res.converged and res.reason == "converged"
    sess = cell.sess
    miss = sess.true_pin(res.joints.positions) - sess.cell.targets[tid].centre
    # half a pixel of size is about 1 % of the stand-off: the depth miss stays within it
    assert np.linalg.norm(miss) < 0.01 * float(sess.cell.p_vt_camera[2])


def test_a_jpeg_cameras_frames_are_what_its_recording_carries(tmp_path: Path) -> None:
    """A live client of a JPEG camera sees the decoded JPEG, not the pixels before it."""
    import tomllib

    from pipeline.io.mcap_write import Recorder
    from pipeline.live.detector import frame_to_grey
    from pipeline.sim.scenario import scenario_from_dict
    from pipeline.stages.ingest.stage import load_image

    raw = tomllib.loads((SCEN / "small.toml").read_text())
    raw["optics"] = {"jpeg_quality": 90}
    sc = scenario_from_dict(raw, where="small-jpeg", base_dir=str(SCEN))
    path = tmp_path / "jpeg.mcap"
    with path.open("wb") as f:
        rec = Recorder(f)
        cell = SimCell.from_scenario(sc, 11, rec)
        cell.robot.move_joints(cell.plan[0][1], 0.5)
        frame = cell.camera.capture()
        rec.finish()
    recorded = load_image(path, "/camera/image_raw/compressed", 0)
    assert np.array_equal(frame_to_grey(frame), recorded)
