"""Adapter strings -> a connected cell: ``--robot`` and ``--camera`` of ``vtcal measure``.

| string | what |
|---|---|
| ``tcp://HOST:PORT`` | a controller speaking the cell protocol (docs/measure.md) |
| ``sim:SCENARIO.toml:SEED`` | the simulated cell, in process |
| ``opencv:0`` / ``opencv:URL`` | an OpenCV ``VideoCapture`` device, stream or file |
| ``folder:/path`` | image files an external tool saves into a folder |
| ``tcp`` (camera) or none | the robot's own link serves ``CAPTURE`` (the simulated cell does) |

With a TCP robot and a camera of its own (OpenCV, folder) the joint states are
polled and stamped on the host clock, the camera's clock (docs/measure.md, "Clocks").

Above both :mod:`pipeline.live` (the live adapters) and the simulated cell
(:mod:`pipeline.sim.link`): it sits in :mod:`pipeline.sim`, the package above
:mod:`pipeline.live` (the simulator runs the live loop), so neither package imports
the other both ways.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pipeline.errors import BadInput
from pipeline.live.cell_link import CellLink
from pipeline.live.protocols import Camera


def _camera(spec: str) -> tuple[Camera, Callable[[], None]]:
    kind, _, rest = spec.partition(":")
    if kind == "opencv" and rest:
        from pipeline.live.cameras import OpenCVCamera

        oc = OpenCVCamera(
            int(rest) if rest.isdigit() else rest, discard=0 if Path(rest).is_file() else 2
        )
        return oc, oc.close
    if kind == "folder" and rest:
        from pipeline.live.cameras import FolderCamera

        fc = FolderCamera(rest)
        return fc, fc.close
    raise BadInput(f"--camera {spec!r}: expected opencv:INDEX|URL, folder:PATH or tcp")


def _sim(spec: str, camera: str | None) -> CellLink:
    from pipeline.sim.link import connect_sim

    if camera not in (None, "sim"):
        raise BadInput(
            f"--camera {camera!r}: the simulated cell has its own camera (omit --camera)"
        )
    return connect_sim(spec)


def connect(robot: str, camera: str | None) -> CellLink:
    """Connect the adapters named by ``robot`` and ``camera`` (see the module doc).

    Raises
    ------
    BadInput
        An adapter string that names no adapter.
    MeasureFault
        The cell does not answer (``connection``).
    """
    if robot.startswith("sim:"):
        return _sim(robot, camera)
    if robot.startswith("tcp://"):
        from pipeline.live.tcp_robot import TcpCamera, TcpRobot

        own = camera in (None, "tcp", robot)
        tr = TcpRobot(robot, host_clock=not own)
        link = CellLink(tr, TcpCamera(tr.link), tr.drain_joints, None, {}, "", [tr.close])
        try:
            if not own:
                assert camera is not None
                link.camera, close = _camera(camera)
                link.closers.append(close)
            link.urdf = tr.fetch_urdf()
            link.metadata = tr.fetch_metadata()
        except BaseException:
            link.close()
            raise
        link.description = (
            f"robot {robot} (joint states: {tr.joint_source}), camera {camera or robot}"
        )
        return link
    raise BadInput(f"--robot {robot!r}: expected tcp://HOST:PORT or sim:SCENARIO.toml:SEED")
