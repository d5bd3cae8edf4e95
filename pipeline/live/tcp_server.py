"""The reference server of the vtcal cell protocol: any :class:`Robot` and :class:`Camera` on a port.

``vtcal cell-server`` runs it around the simulated cell; a controller
programmer reads it as the executable form of docs/measure.md ("The cell
protocol"). One thread per connection (the client polls ``JOINTS?`` on a
second connection while a move blocks the first); one lock around the cell, so
the robot and camera see one call at a time.

A :class:`~pipeline.live.protocols.MeasureFault` of the cell becomes
``ERR kind message``; any other exception closes the connection (what a
crashed controller program does), which the client reports as a lost
connection.
"""

from __future__ import annotations

import socketserver
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.live import wire
from pipeline.live.protocols import Camera, JointReading, MeasureFault, Robot


@dataclass
class Cell:
    """What the server serves.

    Attributes
    ----------
    robot : the arm
    camera : the camera (None: ``CAPTURE`` is unsupported)
    joint_log : ``since_ns -> samples with stamp > since_ns`` (None: ``JOINTLOG?``
        is unsupported and clients poll ``JOINTS?``)
    urdf : the nominal URDF the controller works with (None: ``URDF?`` unsupported)
    metadata : the recording's ``touchup`` keys the cell knows (None: ``META?`` unsupported)
    """

    robot: Robot
    camera: Camera | None = None
    joint_log: Callable[[int], list[JointReading]] | None = None
    urdf: str | None = None
    metadata: dict[str, str] | None = None


class _Handler(socketserver.StreamRequestHandler):
    server: CellServer

    def handle(self) -> None:
        while True:
            try:
                raw = self.rfile.readline()
            except OSError:
                return
            if not raw:
                return
            line = raw.decode("ascii", "replace").strip()
            if not line:
                continue
            try:
                with self.server.lock:
                    reply, payload = self.server.answer(line)
            except MeasureFault as exc:
                reply, payload = wire.error_line(exc.kind, str(exc)), b""
            except _BadRequest as exc:
                reply, payload = wire.error_line("connection", str(exc)), b""
            except Exception as exc:  # noqa: BLE001 - a crashed cell drops the link
                print(f"vtcal cell-server: {line.split()[0]}: {exc}; closing", file=sys.stderr)
                return
            try:
                self.wfile.write(reply.encode("ascii") + b"\n" + payload)
                self.wfile.flush()
            except OSError:
                return
            if line == "BYE":
                return


class _BadRequest(Exception):
    pass


def _numbers(fields: list[str], n: int, command: str) -> np.ndarray:
    if len(fields) != n:
        raise _BadRequest(f"{command} takes {n} numbers, got {len(fields)}")
    try:
        return np.array([float(f) for f in fields])
    except ValueError:
        raise _BadRequest(f"{command}: not numbers: {fields!r}") from None


class CellServer(socketserver.ThreadingTCPServer):
    """A threading TCP server answering the cell protocol for ``cell``.

    Parameters
    ----------
    cell : what to serve
    host, port : where to listen (port 0: a free port, see :attr:`port`)
    """

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, cell: Cell, host: str = "127.0.0.1", port: int = 0) -> None:
        super().__init__((host, port), _Handler)
        self.cell = cell
        self.lock = threading.Lock()
        self.commands = 0

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    def answer(self, line: str) -> tuple[str, bytes]:
        """The reply line (and bytes after it) to one request line."""
        self.commands += 1
        cmd, *args = line.split()
        robot = self.cell.robot
        n = len(robot.joint_names)
        if cmd == "HELLO":
            return f"OK {wire.PROTOCOL} {wire.VERSION}", b""
        if cmd == "NAMES?":
            return "OK " + " ".join(robot.joint_names), b""
        if cmd == "JOINTS?":
            r = robot.read_joints()
            return f"OK {int(r.stamp_ns)} {wire.floats(r.positions)}", b""
        if cmd == "MOVEJ":
            v = _numbers(args, n + 1, cmd)
            if not 0.0 < v[-1] <= 1.0:
                raise _BadRequest(f"MOVEJ speed {v[-1]} not in (0, 1]")
            robot.move_joints(v[:n], float(v[-1]))
            return "OK", b""
        if cmd == "MOVEL_FLANGE":
            robot.move_flange(_numbers(args, 3, cmd))
            return "OK", b""
        if cmd == "STILL?":
            return f"OK {int(bool(robot.is_still()))}", b""
        if cmd == "WAIT":
            robot.wait(float(_numbers(args, 1, cmd)[0]))
            return "OK", b""
        if cmd == "JOINTLOG?" and self.cell.joint_log is not None:
            try:
                since = int(args[0]) if len(args) == 1 else None
            except ValueError:
                since = None
            if since is None:
                raise _BadRequest(f"JOINTLOG? takes one integer stamp, got {args!r}")
            rows = self.cell.joint_log(since)
            text = "".join(f"{int(r.stamp_ns)} {wire.floats(r.positions)}\n" for r in rows)
            data = text.encode("ascii")
            return f"OK {len(data)}", data
        if cmd == "CAPTURE" and self.cell.camera is not None:
            frame = self.cell.camera.capture()
            return wire.frame_header(frame), wire.frame_payload(frame)
        if cmd == "URDF?" and self.cell.urdf is not None:
            data = self.cell.urdf.encode("utf-8")
            return f"OK {len(data)}", data
        if cmd == "META?" and self.cell.metadata is not None:
            data = "".join(f"{k}={v}\n" for k, v in self.cell.metadata.items()).encode("utf-8")
            return f"OK {len(data)}", data
        if cmd == "BYE":
            return "OK", b""
        return wire.error_line(wire.UNSUPPORTED, f"{cmd} is not implemented by this cell"), b""


def serve_in_thread(cell: Cell, host: str = "127.0.0.1", port: int = 0) -> CellServer:
    """Start a :class:`CellServer` in a daemon thread; ``server.shutdown()`` stops it."""
    server = CellServer(cell, host, port)
    threading.Thread(target=server.serve_forever, name="vtcal-cell-server", daemon=True).start()
    return server
