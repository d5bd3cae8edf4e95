"""vtcal measure's safety: the joint-limit check before any move, the dry run, bad adapters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support.fake_wire_cell import FakeCamera, FakeRobot

from pipeline.cli import main
from pipeline.live.tcp_server import Cell, serve_in_thread
from pipeline.robots import load_urdf


def _plan(path: Path, q: np.ndarray) -> Path:
    df = pd.DataFrame(q, columns=[f"joint_{i + 1}" for i in range(q.shape[1])])
    df.insert(0, "target_id", np.arange(len(q)) % 2)
    df.to_parquet(path)
    return path


def _vtcal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main([*argv])
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(e.value.code or 0), out.out, out.err


@pytest.fixture
def cell():  # type: ignore[no-untyped-def]
    robot = FakeRobot()
    server = serve_in_thread(Cell(robot, FakeCamera(robot), robot.joint_log, load_urdf("lrmate")))
    yield robot, f"tcp://127.0.0.1:{server.port}"
    server.shutdown()
    server.server_close()


def test_a_pose_outside_the_joint_limits_refuses_the_run_before_any_move(
    cell, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:  # type: ignore[no-untyped-def]
    robot, url = cell
    q = np.zeros((4, 6))
    q[2, 1] = np.radians(150.0)  # joint_2 upper limit is 145 deg
    plan = _plan(tmp_path / "plan.parquet", q)
    out = tmp_path / "rec.mcap"
    code, _, err = _vtcal(
        ["measure", "--plan", str(plan), "--robot", url, "--out", str(out), "-q"], capsys
    )
    assert code == 3
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "pose 2" in lines[0] and "joint_2 = 150.00 deg" in lines[0]
    assert robot.speeds == [] and not out.exists()


def test_dry_run_visits_every_pose_slowly_and_records_nothing(
    cell, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:  # type: ignore[no-untyped-def]
    robot, url = cell
    q = np.linspace(-0.3, 0.3, 18).reshape(3, 6)
    plan = _plan(tmp_path / "plan.parquet", q)
    out = tmp_path / "rec.mcap"
    argv = ["measure", "--plan", str(plan), "--robot", url, "--out", str(out), "--dry-run", "-q"]
    code, stdout, _ = _vtcal(argv, capsys)
    assert code == 0 and "visited 3 poses" in stdout
    assert robot.speeds == [0.1, 0.1, 0.1] and np.array_equal(robot.q, q[-1])
    assert not out.exists()


@pytest.mark.parametrize(
    ("robot", "msg"),
    [("ftp://x", "expected tcp://HOST:PORT or sim:"), ("sim:nothing", "expected sim:SCENARIO")],
)
def test_bad_adapter_strings_are_bad_input(
    robot: str, msg: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = _plan(tmp_path / "plan.parquet", np.zeros((1, 6)))
    argv = ["measure", "--plan", str(plan), "--robot", robot, "--out", str(tmp_path / "r.mcap")]
    code, _, err = _vtcal(argv, capsys)
    assert code == 2 and msg in err and len(err.strip().splitlines()) == 1


def test_no_cell_listening_is_one_line_and_exit_4(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    plan = _plan(tmp_path / "plan.parquet", np.zeros((1, 6)))
    argv = [
        "measure",
        "--plan",
        str(plan),
        "--robot",
        f"tcp://127.0.0.1:{port}",
        "--out",
        str(tmp_path / "r.mcap"),
    ]
    code, _, err = _vtcal(argv, capsys)
    assert code == 4 and "connection" in err and "cannot connect" in err
    assert len(err.strip().splitlines()) == 1
