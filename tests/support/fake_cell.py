"""A tiny in-process cell for the touch-up loop's tests: an analytic image model, no rendering.

The "robot" is a flange translating in the base frame (three prismatic joints
= the flange position); its orientation is fixed. The controller executes a
commanded flange translation ``dp`` as ``A dp`` (``A`` near identity: the gap
between nominal and true kinematics). The camera is fixed to the flange by
``(R_fc, t_fc)``; a pinhole of focal length ``f`` sees a disc of diameter ``D``
at ``P_base`` and reports

    (u, v) = (cx + f X / Z, cy + f Y / Z),   s = f D / Z,

with ``(X, Y, Z)`` the disc centre in the camera frame (a fronto-parallel
disc's image long axis to first order). Frames carry a zero image of the
camera's size; the detector looks the measurement up by the frame's stamp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.live.protocols import F64, Frame, JointReading

NS = 1_000_000_000


@dataclass
class FakeCell:
    f: float = 800.0
    cx: float = 319.5
    cy: float = 239.5
    width: int = 640
    height: int = 480
    D: float = 0.01
    R_bf: F64 = field(default_factory=lambda: np.diag([1.0, -1.0, -1.0]))  # looking down
    R_fc: F64 = field(default_factory=lambda: _rz(0.3))
    t_fc: F64 = field(default_factory=lambda: np.array([0.01, 0.0, 0.05]))
    A: F64 = field(default_factory=lambda: np.eye(3))
    P_base: F64 = field(default_factory=lambda: np.array([0.4, 0.05, 0.0]))
    noise_px: float = 0.0
    seed: int = 0
    p: F64 = field(default_factory=lambda: np.zeros(3))
    t_ns: int = 0
    busy_s: float = 0.0  # the robot reports "moving" for this long after each move
    lie_still: int = 0  # is_still() answers True this many times regardless
    hidden: bool = False  # the detector finds nothing
    moves: list[F64] = field(default_factory=list)
    seen: dict[int, tuple[float, float, float] | None] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.still_at_ns = 0

    # ---------------------------------------------------------------- truth
    def camera_point(self, p: F64 | None = None) -> F64:
        """Disc centre in the camera frame at flange position ``p``."""
        p = self.p if p is None else p
        R_bc = self.R_bf @ self.R_fc
        p_c = p + self.R_bf @ self.t_fc
        return R_bc.T @ (self.P_base - p_c)

    def uvs(self, p: F64 | None = None) -> tuple[float, float, float]:
        X, Y, Z = self.camera_point(p)
        return (self.cx + self.f * X / Z, self.cy + self.f * Y / Z, self.f * self.D / Z)

    def jacobian(self) -> F64:
        """Analytic ``d(u, v, 1/s) / d(dp_flange)`` at the current pose (commanded ``dp``)."""
        X, Y, Z = self.camera_point()
        f = self.f
        M = np.array(
            [
                [f / Z, 0.0, -f * X / Z**2],
                [0.0, f / Z, -f * Y / Z**2],
                [0.0, 0.0, 1.0 / (f * self.D)],
            ]
        )
        return M @ (-self.R_fc.T @ self.A)

    def flange_for(self, u: float, v: float, s: float) -> F64:
        """Flange position at which the disc is seen at ``(u, v, s)``."""
        Z = self.f * self.D / s
        X_c = np.array([(u - self.cx) / self.f * Z, (v - self.cy) / self.f * Z, Z])
        R_bc = self.R_bf @ self.R_fc
        return self.P_base - R_bc @ X_c - self.R_bf @ self.t_fc

    # ---------------------------------------------------------------- Robot
    @property
    def joint_names(self) -> list[str]:
        return ["x", "y", "z"]

    def read_joints(self) -> JointReading:
        return JointReading(self.p.copy(), self.t_ns)

    def move_joints(self, q: F64, speed: float) -> None:
        self.p = np.asarray(q, dtype=float).copy()
        self._moved(1.0)

    def move_flange(self, dp_flange_m: F64) -> None:
        dp = np.asarray(dp_flange_m, dtype=float)
        self.moves.append(dp.copy())
        self.p = self.p + self.R_bf @ (self.A @ dp)
        self._moved(0.3)

    def _moved(self, dur_s: float) -> None:
        self.t_ns += int(dur_s * NS)
        self.still_at_ns = self.t_ns + int(self.busy_s * NS)

    def is_still(self) -> bool:
        if self.lie_still > 0:
            self.lie_still -= 1
            return True
        return self.t_ns >= self.still_at_ns

    def wait(self, seconds: float) -> None:
        self.t_ns += int(round(seconds * NS))

    # ---------------------------------------------------------------- Camera
    def capture(self) -> Frame:
        stamp = self.t_ns + 5_000_000
        self.t_ns += 10_000_000
        u, v, s = self.uvs()
        inside = 0.0 <= u < self.width and 0.0 <= v < self.height
        if self.hidden or not inside:
            self.seen[stamp] = None
        else:
            e = self.rng.normal(0.0, self.noise_px, 3)
            self.seen[stamp] = (u + e[0], v + e[1], s + e[2])
        img = np.broadcast_to(np.zeros((1, 1), np.uint8), (self.height, self.width))
        return Frame(img, stamp, "mono8")

    def detect(
        self, frame: Frame, expected_uv: tuple[float, float] | None
    ) -> tuple[float, float, float] | None:
        return self.seen[frame.stamp_ns]


def _rz(a: float) -> F64:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
