"""The two protocols a cell implements to be measured by vtcal: ``Robot`` and ``Camera``.

Everything vtcal needs from a live cell is here, and nothing vendor-specific:
an adapter (the simulated cell, the line-based TCP protocol of docs/measure.md,
an OpenCV capture device, a folder of image files) implements these methods and
the touch-up loop (:mod:`pipeline.live.loop`) does the rest.

Frames and units follow docs/conventions.md: joint positions in rad (m for a
prismatic joint), flange translations in metres expressed in the flange frame,
stamps in integer nanoseconds of the cell's clock (the clock the recording's
``header.stamp`` fields use). Every call blocks until what it asks for is done.

Faults are raised as :class:`MeasureFault` with a ``kind`` the command line maps
to one line and a non-zero exit; the recording written so far is kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

#: the image encodings a :class:`Frame` may carry (those of ``sensor_msgs/Image``
#: the recording spec accepts)
ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8")

#: the fault kinds a :class:`MeasureFault` may name
FAULT_KINDS = (
    "connection",  # the robot or camera stopped answering, or answered nonsense
    "move_refused",  # the controller refused a move (limits, reach, protective stop)
    "camera_timeout",  # no image within the adapter's time limit
    "target_not_found",  # the loop lost the target (raised only where it must stop the run)
    "limits",  # a planned pose outside the joint limits or the declared workspace
)


@dataclass(frozen=True)
class JointReading:
    """Joint positions read from the controller.

    Attributes
    ----------
    positions : (n,) float64
        One value per joint of :attr:`Robot.joint_names`, in that order (rad, or m).
    stamp_ns : int
        When the encoders were read, cell clock (ns).
    """

    positions: F64
    stamp_ns: int


@dataclass(frozen=True)
class Frame:
    """One captured image.

    Attributes
    ----------
    image : (H, W) or (H, W, 3) uint8 / uint16 array
        As the camera delivered it (no conversion); ``encoding`` says how to read it.
    stamp_ns : int
        The middle of the exposure, cell clock (ns): the recording's ``header.stamp``.
    encoding : str
        One of :data:`ENCODINGS`.
    """

    image: npt.NDArray[np.generic]
    stamp_ns: int
    encoding: str


class MeasureFault(RuntimeError):
    """A fault at the robot or camera side; ``kind`` is one of :data:`FAULT_KINDS`."""

    def __init__(self, kind: str, message: str) -> None:
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}")
        super().__init__(message)
        self.kind = kind


@runtime_checkable
class Robot(Protocol):
    """What the touch-up loop needs from an arm.

    ``move_flange`` is a small pure translation of the flange, expressed in the
    flange frame, executed by the controller with its own (nominal) kinematics:
    the probing moves and servo steps of the paper's sec. 2.1.
    """

    @property
    def joint_names(self) -> list[str]:
        """Names of the arm's joints, as in the nominal URDF, in reading order."""
        ...

    def read_joints(self) -> JointReading:
        """Current joint positions and the time they were read."""
        ...

    def move_joints(self, q: F64, speed: float) -> None:
        """Move to joint positions ``q`` at ``speed`` (0-1 of the adapter's maximum); block."""
        ...

    def move_flange(self, dp_flange_m: F64) -> None:
        """Translate the flange by ``dp_flange_m`` (3,), flange frame, metres; block."""
        ...

    def is_still(self) -> bool:
        """True once the arm has stopped and settled (no motion above encoder noise)."""
        ...

    def wait(self, seconds: float) -> None:
        """Let ``seconds`` of cell time pass (a simulated robot advances its clock)."""
        ...


@runtime_checkable
class Camera(Protocol):
    """What the touch-up loop needs from a camera fixed to the flange."""

    def capture(self) -> Frame:
        """Expose and return one image; raise ``MeasureFault('camera_timeout', ...)``."""
        ...
