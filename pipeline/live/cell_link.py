"""A connected cell: the robot and camera adapters and what the recording needs besides."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from pipeline.live.protocols import Camera, JointReading, Robot


@dataclass
class CellLink:
    """A connected cell.

    Attributes
    ----------
    robot, camera : the adapters
    drain_joints : the joint samples since the last call (for ``/joint_states``)
    urdf : the nominal URDF the cell serves, or None (then ``--urdf`` is needed)
    metadata : the ``touchup`` metadata keys the cell knows
    description : one line for the log (adapters and joint-state source)
    closers : called in reverse order by :meth:`close`
    """

    robot: Robot
    camera: Camera
    drain_joints: Callable[[], list[JointReading]]
    urdf: str | None
    metadata: dict[str, str]
    description: str
    closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        for c in reversed(self.closers):
            try:
                c()
            except Exception:  # noqa: BLE001 - closing after a fault must not mask it
                pass
