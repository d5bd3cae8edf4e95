"""The cell protocol over a real socket: client adapter against the reference server."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from support.fake_wire_cell import CrashingRobot, FakeCamera, FakeRobot, RefusingRobot

from pipeline.live.protocols import Camera, MeasureFault, Robot
from pipeline.live.tcp_robot import TcpCamera, TcpRobot
from pipeline.live.tcp_server import Cell, CellServer, serve_in_thread


@pytest.fixture
def served() -> Iterator[tuple[FakeRobot, FakeCamera, CellServer]]:
    robot = FakeRobot()
    camera = FakeCamera(robot)
    server = serve_in_thread(Cell(robot, camera, robot.joint_log))
    yield robot, camera, server
    server.shutdown()
    server.server_close()


def _url(server: CellServer) -> str:
    return f"tcp://127.0.0.1:{server.port}"


def test_commands_round_trip_exactly(served: tuple[FakeRobot, FakeCamera, CellServer]) -> None:
    robot, _, server = served
    client = TcpRobot(_url(server))
    try:
        assert isinstance(client, Robot)
        assert client.joint_names == robot.joint_names
        q = np.array([0.1, -0.2, 1.0 / 3.0, np.pi / 7, -1e-9, 2.5])
        client.move_joints(q, 0.25)
        assert np.array_equal(robot.q, q)  # repr floats read back bit-identical
        assert robot.speeds == [0.25]
        r = client.read_joints()
        assert np.array_equal(r.positions, q) and r.stamp_ns == robot.t_ns
        dp = np.array([1e-3, -2e-3, 0.5e-3])
        client.move_flange(dp)
        assert np.array_equal(robot.flange_moves[-1], dp)
        assert client.is_still() is True
        t = robot.t_ns
        client.wait(0.5)
        assert robot.t_ns - t == 500_000_000
    finally:
        client.close()


def test_joint_log_has_every_sample_once_at_the_robots_rate(
    served: tuple[FakeRobot, FakeCamera, CellServer],
) -> None:
    robot, _, server = served
    client = TcpRobot(_url(server))
    try:
        assert client.joint_source == "JOINTLOG?"
        t0 = client.read_joints().stamp_ns
        got = []
        for k in range(4):
            client.move_joints(robot.q + 0.05 * (k + 1), 0.5)
            got += client.drain_joints()
        stamps = np.array([r.stamp_ns for r in got])
        want = np.array([r.stamp_ns for r in robot.log if r.stamp_ns > t0])
        assert np.array_equal(stamps, want)
        assert np.max(np.diff(stamps)) <= 20_000_000  # >= 50 Hz
        assert np.array_equal(got[-1].positions, robot.q)
    finally:
        client.close()


def test_without_jointlog_a_poller_samples_at_least_50_hz() -> None:
    robot = FakeRobot()
    server = serve_in_thread(Cell(robot, None, None))
    client = TcpRobot(f"tcp://127.0.0.1:{server.port}", poll_hz=100.0)
    try:
        assert client.joint_source.startswith("poller")
        client.drain_joints()
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 0.5:
            robot.t_ns += 1_000_000  # the cell's clock runs (a real one would)
            time.sleep(0.001)
        n = len(client.drain_joints())
        rate = n / (time.monotonic() - t0)
        assert rate >= 50.0, rate
    finally:
        client.close()
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "bgr8"])
def test_capture_returns_the_cameras_pixels(encoding: str) -> None:
    robot = FakeRobot()
    camera = FakeCamera(robot, encoding)
    server = serve_in_thread(Cell(robot, camera, robot.joint_log))
    client = TcpRobot(f"tcp://127.0.0.1:{server.port}")
    try:
        cam = TcpCamera(client.link)
        assert isinstance(cam, Camera)
        f = cam.capture()
        camera.count -= 1  # the same image again, locally
        ref = camera.capture()
        assert f.encoding == encoding and f.image.dtype == ref.image.dtype
        assert np.array_equal(f.image, ref.image)
        assert f.stamp_ns == ref.stamp_ns - 10_000_000  # the local capture waited 10 ms more
    finally:
        client.close()
        server.shutdown()
        server.server_close()


def _faulty(robot: FakeRobot) -> tuple[TcpRobot, CellServer]:
    server = serve_in_thread(Cell(robot, FakeCamera(robot), robot.joint_log))
    return TcpRobot(f"tcp://127.0.0.1:{server.port}"), server


def test_a_refused_move_is_a_move_refused_fault() -> None:
    client, server = _faulty(RefusingRobot())
    try:
        with pytest.raises(MeasureFault) as e:
            client.move_joints(np.zeros(6), 0.1)
        assert e.value.kind == "move_refused" and "protective stop" in str(e.value)
        client.read_joints()  # the link survives a refused move
    finally:
        client.close()
        server.shutdown()
        server.server_close()


def test_a_crashed_controller_is_a_connection_fault() -> None:
    client, server = _faulty(CrashingRobot())
    try:
        with pytest.raises(MeasureFault) as e:
            client.move_flange(np.array([1e-3, 0, 0]))
        assert e.value.kind == "connection" and "closed" in str(e.value)
    finally:
        client.close()
        server.shutdown()
        server.server_close()


def test_no_server_and_a_silent_server_are_connection_faults() -> None:
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(MeasureFault) as e:
        TcpRobot(f"tcp://127.0.0.1:{port}")
    assert e.value.kind == "connection"
    quiet = socket.socket()
    quiet.bind(("127.0.0.1", 0))
    quiet.listen(1)  # accepts, never answers
    try:
        with pytest.raises(MeasureFault) as e:
            TcpRobot(f"tcp://127.0.0.1:{quiet.getsockname()[1]}", timeout_s=0.3)
        assert e.value.kind == "connection" and "no reply within 0.3 s" in str(e.value)
    finally:
        quiet.close()


def test_host_clock_polls_and_stamps_with_the_host_clock(
    served: tuple[FakeRobot, FakeCamera, CellServer],
) -> None:
    _, _, server = served
    before = time.time_ns()
    client = TcpRobot(_url(server), host_clock=True)
    try:
        assert client.joint_source == "poller 100 Hz, host clock"
        time.sleep(0.2)
        got = client.drain_joints()
        assert len(got) >= 10
        assert all(before <= r.stamp_ns <= time.time_ns() for r in got)
    finally:
        client.close()


def test_urdf_and_metadata_are_served_when_the_cell_has_them() -> None:
    robot = FakeRobot()
    urdf = "<robot name='r'>\n  <!-- nominal, ünïcode -->\n</robot>\n"
    meta = {"designated_u": "319.5", "polarity": "dark_on_light"}
    server = serve_in_thread(Cell(robot, None, robot.joint_log, urdf, meta))
    bare = serve_in_thread(Cell(robot))
    a = TcpRobot(f"tcp://127.0.0.1:{server.port}")
    b = TcpRobot(f"tcp://127.0.0.1:{bare.port}")
    try:
        assert a.fetch_urdf() == urdf and a.fetch_metadata() == meta
        assert b.fetch_urdf() is None and b.fetch_metadata() == {}
    finally:
        for c, s in ((a, server), (b, bare)):
            c.close()
            s.shutdown()
            s.server_close()
