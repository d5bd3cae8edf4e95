"""The live recording: spec topics, readable after a kill at any point, resumable."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import BadInput
from pipeline.io import mcap as io_mcap
from pipeline.live.protocols import Frame, JointReading
from pipeline.live.record import open_recording, progress_path, read_progress

NAMES = ["j1", "j2"]
URDF = "<robot name='r'/>"
T0 = 1_000_000_000_000


def _touchup(rec, k: int) -> None:  # type: ignore[no-untyped-def]
    """One fake touch-up k: 1 s of joint states at 100 Hz and three captures."""
    t = T0 + k * 1_000_000_000 + 1_000_000
    rec.joints(
        NAMES, [JointReading(np.array([k, i / 100.0]), t + i * 10_000_000) for i in range(100)]
    )
    for c in range(3):
        img = np.full((8, 10), 10 * k + c, np.uint8)
        rec.image(Frame(img, t + 300_000_000 * c + 5_000_000, "mono8"))


def _read(path: Path) -> tuple[io_mcap.StreamState, list[int], list[int]]:
    state = io_mcap.StreamState(str(path))
    joints, images = [], []
    for m in io_mcap.iter_messages(path, state):
        topic = state.topic_type(m.channel_id)[0]
        if topic == "/joint_states":
            joints.append(io_mcap.decode_joint_state(bytes(m.data))[0])
        elif topic == "/camera/image_raw":
            e = io_mcap.decode_image_message("sensor_msgs/msg/Image", "cdr", bytes(m.data))
            images.append(bytes(e.data)[0])
    return state, joints, images


def test_a_killed_recording_is_readable_and_resumes_without_the_unfinished_touchup(
    tmp_path: Path,
) -> None:
    path = tmp_path / "rec.mcap"
    meta = {"threshold_px": "0.5"}
    rec = open_recording(path, URDF, meta, "abc", 4, T0)
    for k in range(2):
        _touchup(rec, k)
        rec.touchup_done({"i": k})
    _touchup(rec, 2)  # killed during touch-up 2: no close, no footer
    killed = tmp_path / "killed.mcap"
    shutil.copy(path, killed)  # what a SIGKILL leaves: every closed chunk is in the file
    state, joints, images = _read(killed)
    assert state.truncated and state.metadata["touchup"] == meta
    assert len(joints) == 300 and images == [0, 1, 2, 10, 11, 12, 20, 21, 22]

    p = read_progress(path)
    assert p is not None and p.done == 2 and not p.finished
    del rec
    rec2 = open_recording(path, URDF, meta, "abc", 4, T0)
    assert rec2.progress.sessions == 2 and rec2.progress.done == 2
    for k in (2, 3):
        _touchup(rec2, k)
        rec2.touchup_done({"i": k})
    rec2.finish()
    state, joints, images = _read(path)
    assert not state.truncated
    assert images == [0, 1, 2, 10, 11, 12, 20, 21, 22, 30, 31, 32]  # touch-up 2 once
    assert joints == sorted(joints) and len(joints) == len(set(joints)) == 400
    assert not path.with_name("rec.mcap.prev").exists()
    p = read_progress(path)
    assert p is not None and p.finished and [t["i"] for t in p.touchups] == [0, 1, 2, 3]


def test_resume_refuses_another_plan_a_finished_run_and_a_foreign_file(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    rec = open_recording(path, URDF, {}, "abc", 1, T0)
    _touchup(rec, 0)
    rec.abandon()
    with pytest.raises(BadInput, match="another plan"):
        open_recording(path, URDF, {}, "xyz", 1, T0)
    rec = open_recording(path, URDF, {}, "abc", 1, T0)
    rec.touchup_done({})
    rec.finish()
    with pytest.raises(BadInput, match="already complete"):
        open_recording(path, URDF, {}, "abc", 1, T0)
    progress_path(path).unlink()
    with pytest.raises(BadInput, match="not a partial"):
        open_recording(path, URDF, {}, "abc", 1, T0)


def test_a_kill_before_the_file_existed_starts_afresh(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    rec = open_recording(path, URDF, {}, "abc", 2, T0)
    rec.abandon()
    path.unlink()  # as if killed between the sidecar and the file
    rec = open_recording(path, URDF, {}, "abc", 2, T0)
    assert rec.progress.sessions == 1 and path.exists()
