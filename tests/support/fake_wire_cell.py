"""A tiny cell for protocol tests: a robot on a simulated clock and a synthetic camera.

Moves are linear in joint space at a fixed joint speed; the robot logs a joint
sample every 10 ms of simulated time (what the simulated cell serves through
``JOINTLOG?``). The camera returns a ramp image stamped with the robot's clock.
"""

from __future__ import annotations

import numpy as np

from pipeline.live.protocols import Frame, JointReading, MeasureFault

NS = 1_000_000_000


class FakeRobot:
    def __init__(self, n: int = 6, rate_hz: float = 100.0) -> None:
        self._names = [f"joint_{i + 1}" for i in range(n)]
        self.q = np.linspace(-0.5, 0.5, n)
        self.t_ns = 1_700_000_000 * NS
        self.dt_ns = int(NS / rate_hz)
        self.log: list[JointReading] = [JointReading(self.q.copy(), self.t_ns)]
        self.flange_moves: list[np.ndarray] = []
        self.speeds: list[float] = []

    @property
    def joint_names(self) -> list[str]:
        return list(self._names)

    def read_joints(self) -> JointReading:
        return JointReading(self.q.copy(), self.t_ns)

    def _advance(self, q_goal: np.ndarray, seconds: float) -> None:
        q0 = self.q.copy()
        steps = max(1, int(round(seconds * NS / self.dt_ns)))
        for k in range(1, steps + 1):
            self.t_ns += self.dt_ns
            self.q = q_goal.copy() if k == steps else q0 + (q_goal - q0) * (k / steps)
            self.log.append(JointReading(self.q.copy(), self.t_ns))

    def move_joints(self, q: np.ndarray, speed: float) -> None:
        q = np.asarray(q, dtype=float)
        self.speeds.append(float(speed))
        self._advance(q, max(0.1, float(np.max(np.abs(q - self.q))) / (speed * 1.0)))

    def move_flange(self, dp_flange_m: np.ndarray) -> None:
        dp = np.asarray(dp_flange_m, dtype=float)
        self.flange_moves.append(dp.copy())
        q = self.q.copy()
        q[:3] += dp
        self._advance(q, 0.2)

    def is_still(self) -> bool:
        return True

    def wait(self, seconds: float) -> None:
        self._advance(self.q.copy(), seconds)

    def joint_log(self, since_ns: int) -> list[JointReading]:
        return [r for r in self.log if r.stamp_ns > since_ns]


class FakeCamera:
    def __init__(self, robot: FakeRobot, encoding: str = "mono8") -> None:
        self.robot = robot
        self.encoding = encoding
        self.count = 0

    def capture(self) -> Frame:
        self.count += 1
        h, w = 24, 32
        ramp = (np.arange(h * w).reshape(h, w) * 37 + self.count) % 256
        if self.encoding == "mono16":
            img = (ramp * 257).astype(np.uint16)
        elif self.encoding in ("rgb8", "bgr8"):
            img = np.stack([ramp, 255 - ramp, ramp // 2], axis=-1).astype(np.uint8)
        else:
            img = ramp.astype(np.uint8)
        self.robot.wait(0.01)
        return Frame(img, self.robot.t_ns, self.encoding)


class RefusingRobot(FakeRobot):
    """Refuses every joint move (a protective stop)."""

    def move_joints(self, q: np.ndarray, speed: float) -> None:
        raise MeasureFault("move_refused", "protective stop: joint 3 outside its limits")


class CrashingRobot(FakeRobot):
    """The controller program dies on the first flange move."""

    def move_flange(self, dp_flange_m: np.ndarray) -> None:
        raise RuntimeError("controller program crashed")
