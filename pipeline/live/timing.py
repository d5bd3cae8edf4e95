"""Where a touch-up's robot time goes: travel, settle, servo and capture, on the cell clock.

:func:`timed` wraps a cell's robot and camera in proxies that note, on the cell
clock (``Robot.read_joints().stamp_ns``, the clock of the touch-up's ``cell_s``),
when each call starts and ends. A touch-up's time from the start of its large move
to its end is then cut into four phases:

- **travel**: the large move (``move_joints``) until the arm arrived;
- **servo**: the small flange moves (probing shifts and servo steps,
  ``move_flange``) until the arm arrived;
- **settle**: from arrival until the next exposure starts: a controller that
  returns from a move only once settled (the simulated one does) spends it inside
  the move call, a live one in the loop's stillness polling (``is_still`` /
  ``wait``);
- **capture**: the exposure, and what follows it until the next move or
  stillness query (detection, recording, the loop's hold after a capture).

*Arrival* is read from the joint states the cell logs while the call runs (the
recording's ``/joint_states``): the first sample from which every later sample of
the call is within ``arrive_tol_rad`` of the call's last one. A call with fewer
than two samples in it counts as arrived at its end. On a cell whose joint states the
client polls and stamps with the host clock while ``JOINTS?`` answers on the
controller's, the cut is only as good as the two clocks agree.

The phases are consecutive stretches of one clock cut at the noted instants, so
they sum to the touch-up's time exactly (integer nanoseconds):

    travel + settle + servo + capture = t_end - t_start                     (T1)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.live.protocols import F64, Camera, Frame, JointReading, Robot

#: the phases of a touch-up's time, in the order they are reported
PHASES = ("travel", "settle", "servo", "capture")
#: a joint within this of where the move ends has arrived (rad; 10 x the simulated
#: encoder noise, a tenth of a typical servo step's joint change)
ARRIVE_TOL_RAD = 1e-5


@dataclass
class PhaseClock:
    """The noted instants of one touch-up: ``(stamp_ns, phase from here on)``.

    Attributes
    ----------
    robot : the wrapped robot (its ``read_joints`` stamp is the clock)
    marks : phase boundaries ``(stamp_ns, phase)`` in time order
    moves : ``(start_ns, end_ns, phase)`` of every move call
    samples : the joint states seen (:meth:`observe`)
    """

    robot: Robot
    marks: list[tuple[int, str]] = field(default_factory=list)
    moves: list[tuple[int, int, str]] = field(default_factory=list)
    samples: list[JointReading] = field(default_factory=list)

    def now(self) -> int:
        return int(self.robot.read_joints().stamp_ns)

    def mark(self, phase: str, t_ns: int | None = None) -> int:
        """From ``t_ns`` (default: now) on, the time is ``phase``'s."""
        t = self.now() if t_ns is None else t_ns
        self.marks.append((t, phase))
        return t

    def start(self) -> int:
        """Start a touch-up: forget the previous one's instants; return the start stamp."""
        self.marks.clear()
        self.moves.clear()
        self.samples.clear()
        return self.mark("travel")

    def observe(self, samples: list[JointReading]) -> None:
        """Joint states the cell logged (as drained for the recording)."""
        self.samples.extend(samples)

    def split(self, t_end_ns: int, arrive_tol_rad: float = ARRIVE_TOL_RAD) -> dict[str, int]:
        """Nanoseconds per phase (:data:`PHASES`) from the first mark to ``t_end_ns``, (T1).

        Each move's stretch from its arrival to its end becomes ``settle``.
        """
        marks = sorted(self.marks + [self._arrival(m, arrive_tol_rad) for m in self.moves])
        out = dict.fromkeys(PHASES, 0)
        for (t, phase), (t_next, _) in zip(marks, [*marks[1:], (t_end_ns, "")], strict=True):
            out[phase] += max(0, min(t_next, t_end_ns) - t)
        return out

    def _arrival(self, move: tuple[int, int, str], tol: float) -> tuple[int, str]:
        """``(arrival stamp, "settle")`` of a move ``(start, end, phase)``."""
        a, b, _ = move
        inside = [s for s in self.samples if a <= s.stamp_ns <= b]
        if len(inside) < 2:
            return b, "settle"
        q = np.array([s.positions for s in inside], dtype=float)
        off = np.max(np.abs(q - q[-1]), axis=1) > tol
        moving = np.flatnonzero(off)
        k = 0 if moving.size == 0 else int(moving[-1]) + 1
        return min(int(inside[k].stamp_ns), b), "settle"


class TimedRobot:
    """A :class:`~pipeline.live.protocols.Robot` that notes its calls on a :class:`PhaseClock`."""

    def __init__(self, robot: Robot, clock: PhaseClock) -> None:
        self.inner = robot
        self.clock = clock
        self._polling = False
        self._after_exposure = False

    @property
    def joint_names(self) -> list[str]:
        return self.inner.joint_names

    def read_joints(self) -> JointReading:
        return self.inner.read_joints()

    def _move(self, phase: str, call: object) -> None:
        a = self.clock.mark(phase)
        self._polling = self._after_exposure = False
        call()  # type: ignore[operator]
        self.clock.moves.append((a, self.clock.now(), phase))

    def move_joints(self, q: F64, speed: float) -> None:
        self._move("travel", lambda: self.inner.move_joints(q, speed))

    def move_flange(self, dp_flange_m: F64) -> None:
        self._move("servo", lambda: self.inner.move_flange(dp_flange_m))

    def is_still(self) -> bool:
        still = self.inner.is_still()
        if self._after_exposure:  # the loop's check that the exposure was still
            self._after_exposure = False
            return still
        if not still and not self._polling:  # waiting for stillness from here on
            self.clock.mark("settle")
            self._polling = True
        return still

    def wait(self, seconds: float) -> None:
        self.inner.wait(seconds)


class TimedCamera:
    """A :class:`~pipeline.live.protocols.Camera` that marks the start of each exposure."""

    def __init__(self, camera: Camera, robot: TimedRobot) -> None:
        self.inner = camera
        self.robot = robot

    def capture(self) -> Frame:
        self.robot.clock.mark("capture")
        self.robot._polling = False
        frame = self.inner.capture()
        self.robot._after_exposure = True
        return frame

    def __getattr__(self, name: str) -> object:  # the adapter's extras (a sim camera's grey_of)
        return getattr(self.inner, name)


def timed(robot: Robot, camera: Camera) -> tuple[TimedRobot, TimedCamera, PhaseClock]:
    """The robot and camera wrapped to note their calls, and the clock they note on."""
    clock = PhaseClock(robot)
    r = TimedRobot(robot, clock)
    return r, TimedCamera(camera, r), clock


def seconds(split_ns: dict[str, int]) -> dict[str, float]:
    """``{phase}_s``: a split in seconds, keyed as the touch-up summaries keep it."""
    return {f"{p}_s": split_ns[p] / 1e9 for p in PHASES}
