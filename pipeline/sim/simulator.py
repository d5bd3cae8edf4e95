"""The simulated touch-up cell: a true robot, a camera, targets, a controller, a recorder.

:func:`simulate` runs one calibration session as the paper describes it and
streams what a real cell would record (``shared/spec/recording.md``) into an
MCAP file, returning the ground truth (written beside it as
``NAME.mcap.truth.json`` by :func:`write_recording`).

The world
    *True robot* = nominal URDF + seeded deviations (:mod:`pipeline.sim.robot`).
    The encoders read the commanded joint angles (plus ``N(0, sigma_enc^2)``
    noise in ``/joint_states``); the flange sits at ``fk(true_chain, q)``.
    *Camera* fixed to the flange at a seeded ``T_flange_camera``; pinhole with
    radial distortion (:mod:`pipeline.sim.camera`), rendered by area coverage
    (:mod:`pipeline.sim.render`). *Targets*: circles on plates in front of the
    robot, normals tilted towards it; two on a calibration bar of known length.

The controller (uses only what a real one has)
    Its own detection of ``(u, v, s)`` on each rendered image
    (:mod:`pipeline.sim.detect`) and the *nominal* chain for every flange
    motion (nominal IK). Per target it first probes the image Jacobian
    ``J = d(u, v, 1/s) / d(p_flange)`` by +-``probe_shift_m`` flange shifts
    (central differences), then runs the loop

        e_T = (u - u0, v - v0, 1/s - 1/s0);  dp = -gain J^{-1} e_T
        T_base_flange <- T_base_flange @ Trans(dp)  (nominal IK)

    until ``|u - u0|, |v - v0| <= threshold_px`` and ``|s - s0| <=
    threshold_size_px`` (then ``repeat_captures - 1`` more still captures) or
    the iteration limit. The robot is still at every capture (settling time
    after each move) unless the capture-while-moving fault says otherwise.

The virtual pin (truth)
    Where a perfect touch-up puts the centre of an untilted target: the circle
    centre whose exactly projected contour (distortion included) fits an
    ellipse with centre ``(u0, v0)`` and long axis ``s0``
    (:func:`virtual_pin_camera`); ``p_vt_flange = T_flange_camera p_vt_camera``.
    Near ``fx D / s0`` on the ray of the designated pixel, but about 10 um nearer
    the camera: barrel distortion shrinks the disc's image even on the axis.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BadInput
from pipeline.kinematics.chain import Chain, fk, load_chain
from pipeline.kinematics.se3 import (
    F64,
    invert_transform,
    matrix_from_axis_angle,
    matrix_from_rpy,
    transform_from,
    translation,
)
from pipeline.kinematics.urdf import parse_urdf
from pipeline.robots import load_urdf
from pipeline.sim.camera import CameraModel
from pipeline.sim.detect import detect_target
from pipeline.sim.optics_state import OpticsState
from pipeline.sim.recorder import Recorder, stamp
from pipeline.sim.render import (
    ExtraDisc,
    Occluder,
    finish_image,
    paint_occluders,
    projected_ellipse,
    render_ideal,
)
from pipeline.sim.robot import (
    deviated_origins,
    draw_deviations,
    solve_ik,
    urdf_with_origins,
    urdf_with_pin,
)
from pipeline.sim.scenario import Scenario

NS = 1_000_000_000
JOINT_LATENCY_NS = 2_000_000

#: Per built-in robot: home joint vector and the centre of the target area (base frame).
ROBOT_CELL: dict[str, dict[str, Any]] = {
    "lrmate": {"home": [0.0, 0.0, 0.0, 0.0, -1.5708, 0.0], "centre": [0.40, 0.0, 0.12]},
    "ur5e": {"home": [0.0, -0.8, 1.6, -2.37, -1.5708, 0.0], "centre": [0.45, 0.0, -0.05]},
    "iiwa7": {"home": [0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0], "centre": [0.55, 0.0, 0.15]},
}

NOTES = (
    "times: *_ns are MCAP log/stamp nanoseconds; *_s are seconds from the recording start. "
    "image_indices count the image topic's messages in log-time order from 0; mcap_sequence is "
    "the Message record's sequence field = index of the message in the file's log-time order. "
    "q are noise-free encoder angles (the joint_states add encoder noise). pin_miss_mm = true pin "
    "- true target centre at the end of the touch-up. Target labels: 0, 1, ... in the order the "
    "run first touches them up (known_distances use labels). visible_fraction: share of the "
    "target disc's image inside the image (0 when occluded). true_ellipse = [u, v, long_axis_px, "
    "short_axis_px, angle_rad] fitted to the exactly projected contour (pose at mid-exposure). "
    "sim_detection is the simulated controller's own (u, v, s)."
)


# --------------------------------------------------------------------------- the cell
@dataclass
class Target:
    id: int
    centre: F64
    normal: F64
    R: F64  # base <- target frame rotation (z = normal)
    history: list[dict[str, Any]] = field(default_factory=list)
    initial: F64 = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.initial = self.centre.copy()

    def T_base_target(self) -> F64:
        return transform_from(self.R, self.centre)


@dataclass
class Cell:
    robot_name: str
    nominal_urdf: str
    true_urdf: str
    true_urdf_with_pin: str
    nominal: Chain
    true: Chain
    deviations: dict[str, Any]
    camera: CameraModel
    T_flange_camera: F64
    p_vt_camera: F64
    p_vt_flange: F64
    u0: float
    v0: float
    s0: float
    targets: list[Target]
    home: F64


def _rot_between(a: F64, b: F64) -> F64:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    v = np.cross(a, b)
    s = float(np.linalg.norm(v))
    c = float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return matrix_from_axis_angle(perp / np.linalg.norm(perp), np.pi)
    return matrix_from_axis_angle(v / s, np.arctan2(s, c))


def _frame_from_normal(n: F64) -> F64:
    z = n / np.linalg.norm(n)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


#: Target frame in the camera frame for an untilted target: plate parallel to the
#: image plane, its normal ``+z`` pointing back at the camera (rotation pi about x).
R_CAMERA_UNTILTED = np.diag([1.0, -1.0, -1.0])


def virtual_pin_camera(
    camera: CameraModel, u0: float, v0: float, s0: float, diameter_m: float, iterations: int = 6
) -> F64:
    """Where a perfect touch-up puts the centre of an untilted target (camera frame).

    The spec (``shared/spec/recording.md``) drives the ellipse fitted to the
    target contour to the designated centre ``(u0, v0)`` and long axis ``s0``.
    For a target whose plate is parallel to the image plane (no tilt: its
    perspective image is a circle) the pin is the circle centre ``p = (X, Y, Z)``
    solving

        E(p) = (u(p) - u0, v(p) - v0, s(p) - s0) = 0,

    with ``(u, v, s)`` the centre and long axis of
    :func:`pipeline.sim.render.projected_ellipse` (the circle's points through
    the full camera model). Without distortion this is ``Z = fx D / s0`` on the
    ray of ``(u0, v0)``. With radial distortion the disc's rim lies at
    normalised radius ``r = D / (2 Z)`` about its centre, and barrel distortion
    (``k1 < 0``) shrinks the image of the disc by ``1 + k1 r^2 + ...`` even at the
    principal point (``-6e-5`` for ``k1 = -0.07``, ``r = 0.03``): a perfect
    touch-up stops about ``Z k1 r^2`` (about 10 um) nearer the camera than
    ``fx D / s0``. Solved by Newton's method, starting from the pinhole answer,
    with a forward-difference Jacobian (``E`` is smooth and nearly linear).

    Parameters
    ----------
    camera : CameraModel
    u0, v0 : float
        Designated centre (px).
    s0 : float
        Designated long axis (px).
    diameter_m : float
        Target diameter ``D``.

    Returns
    -------
    (3,) ``p_vt_camera`` (m).
    """
    xu, yu = camera.pixel_to_normalised(np.array([u0, v0]))
    p = camera.fx * diameter_m / s0 * np.array([xu, yu, 1.0])
    goal = np.array([u0, v0, s0])

    def err(pt: F64) -> F64:
        e = projected_ellipse(camera, transform_from(R_CAMERA_UNTILTED, pt), diameter_m)
        return np.array([e[0], e[1], e[2]]) - goal

    h = 1e-6
    for _ in range(iterations):
        e0 = err(p)
        if np.max(np.abs(e0)) < 1e-9:
            break
        J = np.stack([(err(p + h * np.eye(3)[k]) - e0) / h for k in range(3)], axis=1)
        p = p - np.linalg.solve(J, e0)
    return p


def build_cell(sc: Scenario, rng: np.random.Generator) -> Cell:
    """Draw the true world of one seed: deviations, camera, mount, targets."""
    base_dir = Path(sc.base_dir)
    name = sc.robot.urdf if sc.robot.urdf else sc.robot.name
    nominal_urdf = load_urdf(name, base_dir)
    nominal = load_chain(nominal_urdf, sc.robot.base_link, sc.robot.flange_link)
    deviations = draw_deviations(
        nominal, rng, sc.robot.sigma_xyz_m, sc.robot.sigma_rpy_rad, sc.robot.sigma_q0_rad
    )
    origins = deviated_origins(nominal, deviations)
    true_urdf = urdf_with_origins(nominal_urdf, origins, name_suffix="_true")
    true = load_chain(true_urdf, sc.robot.base_link, sc.robot.flange_link)

    c = sc.camera
    f = c.f_px * (1.0 + rng.uniform(-c.f_jitter, c.f_jitter))
    camera = CameraModel(
        fx=f,
        fy=f,
        cx=(c.width - 1) / 2 + rng.normal(0.0, c.pp_jitter_px),
        cy=(c.height - 1) / 2 + rng.normal(0.0, c.pp_jitter_px),
        k1=c.k1 * (1.0 + rng.uniform(-0.2, 0.2)),
        k2=c.k2 * (1.0 + rng.uniform(-0.2, 0.2)),
        width=c.width,
        height=c.height,
    )
    tilt = rng.normal(0.0, c.mount_tilt_rad, 3)
    R_fc = matrix_from_rpy([0.0, 0.0, np.pi / 2]) @ matrix_from_rpy(tilt)
    p_fc = np.asarray(c.mount_xyz_m, dtype=float) + rng.uniform(
        -c.mount_jitter_m, c.mount_jitter_m, 3
    )
    T_flange_camera = transform_from(R_fc, p_fc)

    t = sc.touchup
    u0 = t.designated_u if t.designated_u is not None else (c.width - 1) / 2
    v0 = t.designated_v if t.designated_v is not None else (c.height - 1) / 2
    D = sc.targets.diameter_m
    s0 = round(camera.fx * D / c.standoff_m, 3)
    p_vt_camera = virtual_pin_camera(camera, float(u0), float(v0), s0, D)
    p_vt_flange = R_fc @ p_vt_camera + p_fc

    cell_defaults = ROBOT_CELL.get(sc.robot.name, ROBOT_CELL["lrmate"])
    home = np.asarray(
        sc.robot.home if sc.robot.home is not None else cell_defaults["home"], dtype=float
    )
    if home.size != nominal.n_dof:
        home = np.clip(np.zeros(nominal.n_dof), nominal.lower, nominal.upper)
    centre = np.asarray(
        sc.targets.centre_m if sc.targets.centre_m is not None else cell_defaults["centre"],
        dtype=float,
    )
    n = sc.targets.count
    targets = []
    for i in range(n):
        y = 0.0 if n == 1 else -0.5 * sc.targets.spread_m + i * sc.targets.spread_m / (n - 1)
        pos = centre + np.array([0.0, y, 0.0]) + rng.uniform(-0.02, 0.02, 3)
        radial = np.array([pos[0], pos[1], 0.0])
        radial /= max(np.linalg.norm(radial), 1e-9)
        tilt_rad = np.deg2rad(sc.targets.tilt_deg) * (1.0 + rng.uniform(-0.3, 0.3))
        normal = np.array([0.0, 0.0, 1.0]) * np.cos(tilt_rad) - radial * np.sin(tilt_rad)
        normal = matrix_from_axis_angle([0.0, 0.0, 1.0], rng.normal(0.0, 0.05)) @ normal
        R = _frame_from_normal(normal)
        targets.append(Target(i, pos, R[:, 2].copy(), R))
    return Cell(
        robot_name=parse_urdf(nominal_urdf).name,
        nominal_urdf=nominal_urdf,
        true_urdf=true_urdf,
        true_urdf_with_pin=urdf_with_pin(true_urdf, sc.robot.flange_link, p_vt_flange),
        nominal=nominal,
        true=true,
        deviations=deviations,
        camera=camera,
        T_flange_camera=T_flange_camera,
        p_vt_camera=p_vt_camera,
        p_vt_flange=p_vt_flange,
        u0=float(u0),
        v0=float(v0),
        s0=float(s0),
        targets=targets,
        home=home,
    )


# --------------------------------------------------------------------------- poses
def measuring_poses(sc: Scenario, cell: Cell, rng: np.random.Generator) -> list[tuple[int, F64]]:
    """Planned ``(target_id, q)`` list: from the plan file or a built-in spread.

    Built-in: per target, view directions ``w`` (target -> camera) in a cone
    of ``cone_half_angle_deg`` about the plate normal (sunflower spread in
    solid angle) and a roll about ``w`` in ``+-roll_range_deg``; the flange
    pose puts a *believed* pin (the true one + a few mm, as taught by hand)
    on the target with the camera looking along ``-w``, solved by nominal IK
    within the joint limits (a draw that fails is replaced by another).
    """
    if sc.poses.plan:
        return _poses_from_plan(sc, cell)
    out: list[tuple[int, F64]] = []
    chain = cell.nominal
    R_fc = cell.T_flange_camera[:3, :3]
    p_vt_believed = cell.p_vt_flange + rng.normal(0.0, 0.002, 3)
    cone = np.deg2rad(sc.poses.cone_half_angle_deg)
    roll_range = np.deg2rad(sc.poses.roll_range_deg)
    K = sc.poses.per_target
    T_home = fk(chain, cell.home)
    az_home = np.arctan2(T_home[1, 3], T_home[0, 3])
    for tg in cell.targets:
        # reference orientation: the home flange orientation turned about the base z axis
        # towards the target (keeps the wrist near its home winding)
        az = np.arctan2(tg.centre[1], tg.centre[0]) - az_home
        R_ref = matrix_from_axis_angle([0.0, 0.0, 1.0], az) @ T_home[:3, :3]
        R_ref_cam = R_ref @ R_fc
        q_prev = cell.home.copy()
        phase = rng.uniform(0, 2 * np.pi)
        found = 0
        attempt = 0
        while found < K and attempt < 40 * K:
            k = found if attempt < K else int(rng.integers(0, K))
            theta = cone * np.sqrt((k + 0.5) / K) if attempt < 2 * K else rng.uniform(0, cone)
            phi = phase + k * 2.399963229728653 + (0.0 if attempt < K else rng.uniform(0, 6.3))
            roll = rng.uniform(-roll_range, roll_range)
            attempt += 1
            n = tg.normal
            e1 = tg.R[:, 0]
            e2 = tg.R[:, 1]
            w = np.cos(theta) * n + np.sin(theta) * (np.cos(phi) * e1 + np.sin(phi) * e2)
            R_cam = matrix_from_axis_angle(w, roll) @ _rot_between(R_ref_cam[:, 2], -w) @ R_ref_cam
            R_flange = R_cam @ R_fc.T
            p_flange = tg.centre - R_flange @ p_vt_believed
            T_goal = transform_from(R_flange, p_flange)
            seeds = [q_prev, cell.home] + [
                rng.uniform(np.maximum(chain.lower, -np.pi), np.minimum(chain.upper, np.pi))
                for _ in range(3)
            ]
            for seed in seeds:
                q, ok = solve_ik(chain, T_goal, seed, q_rest=cell.home, max_iter=150)
                if ok:
                    out.append((tg.id, q))
                    q_prev = q
                    found += 1
                    break
        if found < K:
            raise BadInput(
                f"scenario {sc.name}: only {found} of {K} measuring poses of target {tg.id} "
                f"at {np.round(tg.centre, 3).tolist()} are reachable; move the targets "
                "([targets] centre_m) or narrow [poses] cone_half_angle_deg"
            )
    return out


#: a plan made for a pin farther than this from the cell's starts its touch-ups too far off:
#: a third of the half field of view of the standard cells at their stand-off (17 mm off
#: worked in docs/planner.md's example, 69 mm (the planner's default pin) lost 34 of 36)
MAX_PLAN_PIN_OFFSET_M = 0.03


def _check_plan_pin(path: Path, cell: Cell) -> None:
    """Refuse a plan made (``vtcal plan --pin``) for another virtual pin than this cell's.

    The planner puts the pin it was given on each target; the cell's camera puts its
    own pin there. Farther apart than ``MAX_PLAN_PIN_OFFSET_M``, the touch-ups start
    centimetres off and most are lost.
    """
    import json

    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
        planned = json.loads(meta.get(b"vtcal.plan", b"{}")).get("config", {}).get("p_flange_pin")
    except (OSError, ValueError):
        return
    if planned is None:
        return  # a plan written by hand: nothing to compare
    off = float(np.linalg.norm(np.asarray(planned, dtype=float) - cell.p_vt_flange))
    if off > MAX_PLAN_PIN_OFFSET_M:
        want = ",".join(f"{v:.3f}" for v in cell.p_vt_flange)
        raise BadInput(
            f"{path}: planned for a virtual pin at {[round(float(v), 4) for v in planned]} m in "
            f"the flange frame, but this scenario's camera puts it at "
            f"{[round(float(v), 4) for v in cell.p_vt_flange]} ({1e3 * off:.0f} mm away): every "
            f"pose would miss its target; plan with --pin {want}"
        )


def _poses_from_plan(sc: Scenario, cell: Cell) -> list[tuple[int, F64]]:
    import pandas as pd

    path = Path(str(sc.poses.plan))
    if not path.exists() and not path.is_absolute():
        path = Path(sc.base_dir) / path
    if not path.exists():
        raise BadInput(f"{sc.poses.plan}: plan file not found")
    try:
        df = pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is bad input
        raise BadInput(f"{path}: not a readable Parquet plan ({exc})") from exc
    names = cell.nominal.joint_names
    missing = [c for c in ["target_id", *names] if c not in df.columns]
    if missing:
        raise BadInput(f"{path}: plan lacks columns {missing} (needs target_id and {names})")
    _check_plan_pin(path, cell)
    ids = {t.id for t in cell.targets}
    out = []
    for row in df.itertuples(index=False):
        raw = getattr(row, "target_id")  # noqa: B009
        try:
            tid = int(raw)
        except (TypeError, ValueError):
            raise BadInput(f"{path}: target_id {raw!r} is not an integer target id") from None
        if tid not in ids:
            raise BadInput(f"{path}: target_id {tid} not in the scenario (0..{len(ids) - 1})")
        q = np.array([float(getattr(row, n)) for n in names])
        out.append((tid, q))
    return out


# --------------------------------------------------------------------------- motion + capture
class Robot:
    """Commanded joint motion on a global clock, streaming ``/joint_states``.

    Moves are quintic (``s = 10 t^3 - 15 t^4 + 6 t^5``) in joint space. Joint
    states are emitted on a fixed tick grid (``joint_rate_hz``) with stamp =
    the tick, log time = tick + 2 ms, positions + encoder noise, velocities
    from the trajectory.
    """

    def __init__(
        self,
        rec: Recorder,
        names: list[str],
        q0: F64,
        t0_ns: int,
        rate_hz: float,
        noise_rad: float,
        rng: np.random.Generator,
    ) -> None:
        self.rec = rec
        self.names = names
        self.t = t0_ns
        self.t0 = t0_ns
        self.dt_ns = int(round(NS / rate_hz))
        self.next_tick = t0_ns
        self.noise = noise_rad
        self.rng = rng
        self.seg = (q0.copy(), q0.copy(), t0_ns, 1)
        self.gaps: list[tuple[int, int]] = []
        self.dropped: list[int] = []
        self.emitted = 0
        self.emitted_before_gap: dict[int, int] = {}

    @property
    def q(self) -> F64:
        return self.q_at(self.t)

    def q_at(self, t_ns: float) -> F64:
        qa, qb, ts, dur = self.seg
        tau = np.clip((t_ns - ts) / dur, 0.0, 1.0)
        s = tau**3 * (10 - 15 * tau + 6 * tau * tau)
        return qa + (qb - qa) * s

    def v_at(self, t_ns: float) -> F64:
        qa, qb, ts, dur = self.seg
        tau = (t_ns - ts) / dur
        if tau <= 0.0 or tau >= 1.0:
            return np.zeros_like(qa)
        ds = 30 * tau**2 * (1 - tau) ** 2 / (dur / NS)
        return (qb - qa) * ds

    def moving_at(self, t_ns: float) -> bool:
        qa, qb, ts, dur = self.seg
        return bool(ts < t_ns < ts + dur and np.any(qa != qb))

    def start_move(self, q_goal: F64, duration_s: float) -> None:
        self.seg = (
            self.q.copy(),
            np.asarray(q_goal, dtype=float).copy(),
            self.t,
            int(duration_s * NS),
        )

    def move_duration(self, q_goal: F64, speed: float, minimum: float) -> float:
        dq = float(np.max(np.abs(np.asarray(q_goal) - self.q)))
        return max(minimum, 1.875 * dq / speed)

    def align_to_tick(self) -> None:
        """Advance the clock to the next joint-state tick (emitting it): the time
        from here to every later tick is then a whole number of ticks."""
        if self.t != self.next_tick - self.dt_ns:
            self.advance((self.next_tick - self.t) / NS)

    def advance(self, dt_s: float) -> None:
        t_end = self.t + int(round(dt_s * NS))
        while self.next_tick <= t_end:
            tk = self.next_tick
            self.next_tick += self.dt_ns
            in_gap = [g for g, (a, b) in enumerate(self.gaps) if a <= tk < b]
            if in_gap:
                self.dropped.append(tk)
                self.emitted_before_gap.setdefault(in_gap[0], self.emitted)
                continue
            pos = self.q_at(tk) + self.rng.normal(0.0, self.noise, len(self.names))
            vel = self.v_at(tk)
            msg = {
                "header": {"stamp": stamp(tk), "frame_id": ""},
                "name": self.names,
                "position": [float(x) for x in pos],
                "velocity": [float(x) for x in vel],
                "effort": [],
            }
            self.rec.push(tk + JOINT_LATENCY_NS, "/joint_states", "sensor_msgs/msg/JointState", msg)
            self.emitted += 1
        self.t = t_end
        self.rec.flush(self.t)


@dataclass
class CaptureOptions:
    extra_discs: tuple[ExtraDisc, ...] = ()
    occluders: tuple[Occluder, ...] = ()


class Session:
    """One simulated calibration session (the controller + the world + the recorder)."""

    def __init__(self, sc: Scenario, seed: int, rec: Recorder) -> None:
        self.sc = sc
        self.seed = seed
        ss = np.random.SeedSequence(seed)
        streams = ss.spawn(6)
        self.rng_cell = np.random.default_rng(streams[0])
        self.rng_pose = np.random.default_rng(streams[1])
        self.rng_img = np.random.default_rng(streams[2])
        self.rng_enc = np.random.default_rng(streams[3])
        self.rng_fault = np.random.default_rng(streams[4])
        self.rec = rec
        self.cell = build_cell(sc, self.rng_cell)
        self.optics = OpticsState(
            sc,
            seed,
            [t.id for t in self.cell.targets],
            self.cell.camera,
            float(self.cell.p_vt_camera[2]),
        )
        self.polarity = sc.targets.polarity
        lv = sc.targets.levels
        if self.polarity == "dark_on_light":
            self.levels = (lv[0], lv[1])
            self.background = lv[2]
        else:
            self.levels = (lv[1], lv[0])
            self.background = 1.5 * lv[0]
        self.images: list[dict[str, Any]] = []
        self.touchups: list[dict[str, Any]] = []
        self.probes: list[dict[str, Any]] = []
        self.faults: list[dict[str, Any]] = []
        self.compressed = sc.camera.image == "png" or sc.optics.jpeg_quality > 0
        self.image_topic = (
            "/camera/image_raw/compressed" if self.compressed else "/camera/image_raw"
        )
        self.robot: Robot | None = None
        self.last_renders = 1
        self.safe_bytes = 0

    # ------------------------------------------------------------ helpers
    def reseed(self, plan_index: int, faulted: bool) -> None:
        """Give the touch-up at plan pose ``plan_index`` its own image and encoder noise.

        The streams come from ``SeedSequence(seed, spawn_key=(1000, plan_index,
        faulted))``: a touch-up's noise depends on the seed and its plan pose only, not
        on how many images or joint states the touch-ups before it drew.
        """
        ss = np.random.SeedSequence(self.seed, spawn_key=(1000, plan_index, int(faulted)))
        s_img, s_enc = ss.spawn(2)
        self.rng_img = np.random.default_rng(s_img)
        self.rng_enc = np.random.default_rng(s_enc)
        if self.robot is not None:
            self.robot.rng = self.rng_enc
        self.optics.reseed(plan_index, faulted)

    def _T_camera_target(self, q: F64, tg: Target) -> F64:
        T_base_cam = fk(self.cell.true, q) @ self.cell.T_flange_camera
        return invert_transform(T_base_cam) @ tg.T_base_target()

    def true_pin(self, q: F64) -> F64:
        T = fk(self.cell.true, q)
        return T[:3, :3] @ self.cell.p_vt_flange + T[:3, 3]

    def capture(
        self,
        tg: Target,
        kind: str,
        touchup: int,
        opts: CaptureOptions | None = None,
        expected_uv: tuple[float, float] | None = None,
    ) -> tuple[float, float, float] | None:
        """Expose, render, encode and queue one image; return the controller's detection."""
        rob = self.robot
        assert rob is not None
        opts = opts or CaptureOptions()
        sc = self.sc
        exp_ns = int(sc.camera.exposure_s * NS)
        t_start = rob.t
        moving = rob.moving_at(t_start) or rob.moving_at(t_start + exp_ns)
        if moving:
            exp_ns = int(max(sc.camera.exposure_s, 0.04) * NS)
        n_sub = 1
        op = self.optics
        if moving:
            # enough sub-exposure renders that consecutive copies are < 0.5 px apart
            ends = [self._T_camera_target(rob.q_at(t), tg) for t in (t_start, t_start + exp_ns)]
            sweep = float(np.linalg.norm(cam_project(self, ends[1]) - cam_project(self, ends[0])))
            n_sub = int(np.clip(np.ceil(sweep / 0.5), 5, 40))
        elif op.vibration.active:
            n_sub = 3  # the camera still shakes during the exposure
        times = [t_start + exp_ns * (k + 0.5) / n_sub for k in range(n_sub)]
        qs = [rob.q_at(t) for t in times]
        Ts = np.stack(
            [op.shaken(self._T_camera_target(q, tg), t) for q, t in zip(qs, times, strict=True)]
        )
        cam = self.cell.camera
        D = sc.targets.diameter_m
        shape = op.shapes.get(tg.id)
        ideal = render_ideal(
            cam,
            Ts,
            D,
            levels=self.levels,
            plate_radius_m=sc.targets.plate_radius_m,
            background_grey=self.background,
            extra_discs=opts.extra_discs,
            subsamples=sc.camera.subsamples,
            blur_sigma_px=sc.camera.blur_sigma_px,
            target_shape=shape,
            light=op.lights.get(tg.id),
            defocus=op.defocus,
        )
        if op.sensor_active:
            img, grey = op.form(paint_occluders(ideal, opts.occluders))
        else:
            img = finish_image(
                ideal,
                cam,
                blur_sigma_px=0.0,
                noise_sigma=sc.camera.noise_sigma,
                vignetting=sc.camera.vignetting,
                rng=self.rng_img,
                occluders=opts.occluders,
            )
            grey = img
        det = detect_target(
            grey,
            self.polarity,
            expected_uv=expected_uv or (self.cell.u0, self.cell.v0),
            method=sc.touchup.controller,
        )
        t_mid = t_start + exp_ns // 2
        q_mid = rob.q_at(t_mid)
        T_mid = op.shaken(self._T_camera_target(q_mid, tg), t_mid)
        centre_px = cam.project(T_mid[:3, 3])
        ell = projected_ellipse(cam, T_mid, D, shape=shape)
        blur_px = 0.0
        if moving:
            c = np.array([cam.project(T[:3, 3]) for T in Ts])
            blur_px = float(np.linalg.norm(c[-1] - c[0]) * n_sub / max(n_sub - 1, 1))
        self.last_renders = n_sub
        stamp_ns = t_mid
        log_ns = t_start + exp_ns + int(sc.camera.latency_s * NS)
        rec = {
            "index": -1,
            "stamp_s": (stamp_ns - rob.t0) / NS,
            "log_s": (log_ns - rob.t0) / NS,
            "kind": kind,
            "touchup": touchup,
            "target": tg.id,
            "moving": bool(moving),
            "screw": False,
            "occluded": bool(opts.occluders),
            "second_blob": bool(opts.extra_discs),
            "visible_fraction": 0.0 if opts.occluders else 1.0,
            "q_true": [float(x) for x in q_mid],
            "sim_detection": None if det is None else [float(x) for x in det],
            "sim_detection_cut": False,
            "true_centre_px": [float(x) for x in centre_px],
            "true_ellipse": [float(x) for x in ell],
            "blur_px": blur_px,
            "mcap_sequence": -1,
            "in_file": True,
            "log_time_ns": int(log_ns),
            "stamp_ns": int(stamp_ns),
        }
        self.images.append(rec)
        if self.compressed:
            fmt, data = op.encode(img)
            msg: dict[str, Any] = {
                "header": {"stamp": stamp(stamp_ns), "frame_id": "camera_optical_frame"},
                "format": fmt,
                "data": data,
            }
            datatype = "sensor_msgs/msg/CompressedImage"
        else:
            colour = img.ndim == 3
            msg = {
                "header": {"stamp": stamp(stamp_ns), "frame_id": "camera_optical_frame"},
                "height": cam.height,
                "width": cam.width,
                "encoding": "bgr8" if colour else "mono8",
                "is_bigendian": 0,
                "step": cam.width * (3 if colour else 1),
                "data": np.ascontiguousarray(img).tobytes(),
            }
            datatype = "sensor_msgs/msg/Image"

        def on_write(idx: int, seq: int, rec: dict[str, Any] = rec) -> None:
            rec["index"] = idx
            rec["mcap_sequence"] = seq

        self.rec.push(log_ns, self.image_topic, datatype, msg, on_write)
        rob.advance(exp_ns / NS)
        return det

    def nominal_shift(self, q: F64, dp_flange: F64) -> F64:
        """Joint vector moving the *nominal* flange by ``dp_flange`` (flange frame)."""
        T_goal = fk(self.cell.nominal, q) @ translation(dp_flange)
        q_new, _ = solve_ik(self.cell.nominal, T_goal, q, max_iter=50, respect_limits=False)
        return q_new

    def nominal_roll(self, q: F64, angle_rad: float) -> F64:
        """Joint vector rolling the *nominal* flange by ``angle_rad`` about the camera's
        optical axis through the virtual pin: the same target, seen from a pose the
        touch-up extraction takes for another touch-up (an extra, faulted attempt)."""
        axis_flange = self.cell.T_flange_camera[:3, 2]
        R = matrix_from_axis_angle(axis_flange, angle_rad)
        pin = self.cell.p_vt_flange
        T_rot = np.eye(4)
        T_rot[:3, :3] = R
        T_rot[:3, 3] = pin - R @ pin
        T_goal = fk(self.cell.nominal, q) @ T_rot
        q_new, _ = solve_ik(self.cell.nominal, T_goal, q, max_iter=50, respect_limits=False)
        return q_new

    def small_move(self, q_goal: F64) -> None:
        rob = self.robot
        assert rob is not None
        dur = rob.move_duration(q_goal, self.sc.timing.max_speed_rad_s, 0.3)
        rob.start_move(q_goal, dur)
        self.optics.on_move(rob.t + dur * NS)
        rob.advance(dur + self.sc.timing.settle_s)

    def _blur_fraction(self, tg: Target, dur: float, latest: float, want_px: float = 4.0) -> float:
        """Latest fraction of the current move (<= ``latest``) whose exposure smears >= want_px."""
        rob = self.robot
        assert rob is not None
        exp_ns = max(self.sc.camera.exposure_s, 0.04) * NS
        t0 = rob.t
        for frac in np.arange(latest, 0.3, -0.02):
            ta = t0 + frac * dur * NS
            a = cam_project(self, self._T_camera_target(rob.q_at(ta), tg))
            b = cam_project(self, self._T_camera_target(rob.q_at(ta + exp_ns), tg))
            if np.linalg.norm(b - a) >= want_px:
                return float(frac)
        return 0.3

    def large_move(
        self, q_goal: F64, stop_at: float | None = None, tg: Target | None = None
    ) -> None:
        """Move to ``q_goal`` and settle; with ``stop_at`` return mid-move (blurred capture)."""
        rob = self.robot
        assert rob is not None
        dur = rob.move_duration(q_goal, self.sc.timing.max_speed_rad_s, 0.8)
        rob.start_move(q_goal, dur)
        self.optics.on_move(rob.t + dur * NS)
        if stop_at is not None and tg is not None:
            rob.advance(self._blur_fraction(tg, dur, stop_at) * dur)
            return
        rob.advance(dur + self.sc.timing.settle_s)


def cam_project(sess: Session, T_camera_target: F64) -> F64:
    """Pixel of the target centre (for blur estimates)."""
    return sess.cell.camera.project(T_camera_target[:3, 3])


def _measure(det: tuple[float, float, float]) -> F64:
    return np.array([det[0], det[1], 1.0 / det[2]])


def simulate(sc: Scenario, seed: int, out: Path) -> dict[str, Any]:
    """Run the session of scenario ``sc`` with ``seed``; write ``out`` (MCAP) and return the truth.

    The MCAP file is written streaming; the truth dictionary has the layout
    of the conformance sample's truth file (see module doc of
    :mod:`pipeline.sim`).
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    with tmp.open("wb") as f:
        rec = Recorder(f, chunk_size=sc.timing.chunk_size)
        sess = Session(sc, seed, rec)
        truth = _run(sess)
        rec.finish()
    os.replace(tmp, out)
    if sc.faults.truncate:
        truth["truncated"] = _truncate(out, truth, sess.rng_fault, sess.safe_bytes)
    return truth


def _fault_plan(sess: Session, plan: list[tuple[int, F64]]) -> dict[str, int]:
    """Which touch-up (index) carries which fault; -1 if off."""
    fl = sess.sc.faults
    first_of: dict[int, int] = {}
    for i, (tid, _) in enumerate(plan):
        first_of.setdefault(tid, i)
    candidates = [i for i in range(len(plan)) if i not in first_of.values()]
    rng = sess.rng_fault
    order = list(rng.permutation(candidates)) if candidates else []
    names = ["capture_while_moving", "second_blob", "unconverged", "lost_target", "joint_state_gap"]
    out: dict[str, int] = {}
    k = 0
    for nm in names:
        if getattr(fl, nm) and order:
            out[nm] = int(order[k % len(order)])
            k += 1
        else:
            out[nm] = -1
    out["knocked_target"] = -1
    if fl.knocked_target:
        # knock a target between two of its touch-ups (before a non-first one)
        later = [i for i in candidates if i > first_of[plan[i][0]]]
        if later:
            out["knocked_target"] = int(later[len(later) // 2])
    return out


#: Roll of an extra, faulted touch-up off its plan pose, rad (about 3.4 degrees).
FAULT_ROLL_RAD = 0.06


def _attempts(n_plan: int, faults_at: dict[str, int]) -> list[tuple[int, bool]]:
    """The touch-ups of a session in order: ``(plan index, faulted)``.

    A fault never takes the place of a planned touch-up: a plan pose that carries a
    fault (other than a knock, which happens between touch-ups) is visited twice,
    first by an extra, faulted touch-up at the pose rolled by
    :data:`FAULT_ROLL_RAD` about the camera axis through the pin (so that it is a
    touch-up of its own, not a continuation of the next), then by the planned one.
    A recording with faults thus holds every touch-up of the same seed's
    fault-free recording (with the same noise, see :meth:`Session.reseed`) plus
    the faulted ones.
    """
    faulted = {i for nm, i in faults_at.items() if nm != "knocked_target" and i >= 0}
    out: list[tuple[int, bool]] = []
    for i in range(n_plan):
        if i in faulted:
            out.append((i, True))
        out.append((i, False))
    return out


def _run(sess: Session) -> dict[str, Any]:
    sc = sess.sc
    cell = sess.cell
    rec = sess.rec
    tt = sc.touchup
    plan = measuring_poses(sc, cell, sess.rng_pose)
    labels: dict[int, int] = {}
    for tid, _ in plan:
        labels.setdefault(tid, len(labels))
    faults_at = _fault_plan(sess, plan)
    safe_bytes = 0
    if sc.faults.truncate:
        # one more touch-up (a repeat of the first pose) during which the recorder dies
        plan = plan + [plan[0]]
    attempts = _attempts(len(plan), faults_at)
    tail_index = len(attempts) - 1 if sc.faults.truncate else -1

    t0 = sc.timing.start_ns
    rec.push(t0, "/robot_description", "std_msgs/msg/String", {"data": cell.nominal_urdf})
    rec.flush(t0)
    # known distances (bar between the first and last target)
    known: list[dict[str, Any]] = []
    if sc.targets.bar and len(cell.targets) >= 2:
        a, b = cell.targets[0], cell.targets[-1]
        if a.id in labels and b.id in labels:
            d = float(np.linalg.norm(a.centre - b.centre))
            la, lb = sorted((labels[a.id], labels[b.id]))
            ida, idb = (a.id, b.id) if labels[a.id] <= labels[b.id] else (b.id, a.id)
            known.append(
                {
                    "labels": [la, lb],
                    "target_ids": [ida, idb],
                    "metres": round(d, 6),
                    "true_metres": d,
                }
            )
    metadata = {
        "base_link": sc.robot.base_link,
        "flange_link": sc.robot.flange_link,
        "target_diameter_m": f"{sc.targets.diameter_m:.3f}",
        "designated_u": f"{cell.u0:g}",
        "designated_v": f"{cell.v0:g}",
        "designated_size_px": f"{cell.s0:.3f}",
        "threshold_px": f"{tt.threshold_px:g}",
        "threshold_size_px": f"{tt.threshold_size_px:g}",
        "polarity": sc.targets.polarity,
    }
    if known:
        metadata["known_distances"] = ";".join(
            f"{k['labels'][0]}:{k['labels'][1]}={k['metres']:.6f}" for k in known
        )
    rec.metadata("touchup", metadata)

    rob = Robot(
        rec,
        cell.nominal.joint_names,
        cell.home,
        t0,
        sc.timing.joint_rate_hz,
        sc.timing.encoder_noise_rad,
        sess.rng_enc,
    )
    sess.robot = rob
    rob.advance(1.0)

    targets = {t.id: t for t in cell.targets}
    jac: dict[int, F64] = {}
    u0, v0, s0 = cell.u0, cell.v0, cell.s0
    goal = np.array([u0, v0, 1.0 / s0])

    for ti, (pi, faulted) in enumerate(attempts):
        tid, q_plan = plan[pi]
        if faulted:  # an extra attempt, rolled off the plan pose (docstring of _attempts)
            q_plan = sess.nominal_roll(q_plan, FAULT_ROLL_RAD)
        tg = targets[tid]
        img_start = len(sess.images)
        gain = tt.gain
        opts = CaptureOptions()
        fault_here: list[dict[str, Any]] = []
        # the faults of this attempt: plan index -> fault, on the extra attempt only
        here = {nm: faulted and i == pi for nm, i in faults_at.items()}
        if faults_at["knocked_target"] == pi and (ti == 0 or attempts[ti - 1][0] != pi):
            shift = sess.rng_fault.normal(0.0, 1.0, 3)
            shift *= sess.rng_fault.uniform(0.001, 0.002) / np.linalg.norm(shift)
            tg.centre = tg.centre + shift
            tg.history.append(
                {"from_s": (rob.t - t0) / NS, "from_ns": int(rob.t), "centre": tg.centre.tolist()}
            )
            sess.faults.append(
                {
                    "type": "target_knocked",
                    "target": tid,
                    "label": labels[tid],
                    "time_s": (rob.t - t0) / NS,
                    "shift_m": shift.tolist(),
                    "first_touchup": ti,
                    "centre_after": tg.centre.tolist(),
                    "time_ns": int(rob.t),
                    "touchups_after": [
                        i for i in range(ti, len(attempts)) if plan[attempts[i][0]][0] == tid
                    ],
                }
            )
        if here["unconverged"]:
            gain = 0.2
            offset = sess.rng_fault.normal(0.0, 1.0, 3)
            offset[2] = 0.0
            offset *= 0.01 / np.linalg.norm(offset)
            q_plan = sess.nominal_shift(q_plan, offset)
            fault_here.append({"type": "unconverged", "gain": gain, "plan_offset_m": 0.01})
        if here["second_blob"]:
            ang = sess.rng_fault.uniform(0, 2 * np.pi)
            rad = sess.rng_fault.uniform(0.013, 0.02)
            off = (float(rad * np.cos(ang)), float(rad * np.sin(ang)))
            opts.extra_discs = ((off[0], off[1], 0.004, float(sess.levels[0])),)
            fault_here.append(
                {"type": "second_blob", "diameter_m": 0.004, "offset_in_plate_m": list(off)}
            )
        if here["joint_state_gap"]:
            g0 = rob.t + int(0.3 * NS)
            rob.gaps.append((g0, g0 + int(0.5 * NS)))

        # ---- large move to the planned pose
        n_dropped = len(rob.dropped)
        capture_mid = here["capture_while_moving"]
        if ti == tail_index:
            safe_bytes = rec.cut_chunk()
        sess.large_move(q_plan, stop_at=0.94 if capture_mid else None, tg=tg)
        if not capture_mid:
            # at the planned pose: from here on this touch-up's noise is its own (clock
            # phase and random streams depend on the plan pose only), so a touch-up is
            # the same whatever faulted attempts came before it
            rob.align_to_tick()
        sess.reseed(pi, faulted)
        if here["joint_state_gap"]:
            dropped = rob.dropped[n_dropped:]
            n_pre = rob.emitted_before_gap[len(rob.gaps) - 1]
            sess.faults.append(
                {
                    "type": "joint_state_gap",
                    "touchup": ti,
                    "duration_s": len(dropped) * rob.dt_ns / NS,
                    "missing_stamps_ns": [int(dropped[0]), int(dropped[-1])],
                    "missing_count": len(dropped),
                    "last_index_before": int(n_pre - 1),
                    "first_index_after": int(n_pre),
                    "log_time_before_ns": int(dropped[0] - rob.dt_ns + JOINT_LATENCY_NS),
                    "log_time_after_ns": int(dropped[-1] + rob.dt_ns + JOINT_LATENCY_NS),
                }
            )
        q = q_plan.copy()

        lost = False
        converged = False
        iterations = 0
        final_err: list[float] | None = None
        conv_images: list[int] = []
        expected: tuple[float, float] | None = None

        # ---- lost target: an occluder hides it at the first capture
        if here["lost_target"]:
            occ = (
                float(u0 + sess.rng_fault.normal(0, 5)),
                float(v0 + sess.rng_fault.normal(0, 5)),
                150.0,
                120.0,
                float(sess.rng_fault.uniform(0, np.pi)),
                float(sess.background),
            )
            opts.occluders = (occ,)
            fault_here.append(
                {
                    "type": "target_lost",
                    "cause": "occluded",
                    "occluder": {
                        "centre_px": [occ[0], occ[1]],
                        "semi_axes_px": [occ[2], occ[3]],
                        "angle_rad": occ[4],
                        "grey": occ[5],
                    },
                }
            )

        # ---- image Jacobian probing (first touch-up of each target)
        if tid not in jac and not opts.occluders:
            h = tt.probe_shift_m
            shifts: list[F64] = [np.zeros(3)]
            for ax in range(3):
                for sgn in (1.0, -1.0):
                    dv = np.zeros(3)
                    dv[ax] = sgn * h
                    shifts.append(dv)
            meas = []
            p_imgs = []
            for dv in shifts:
                if np.any(dv):
                    sess.small_move(sess.nominal_shift(q_plan, dv))
                p_imgs.append(len(sess.images))
                det = sess.capture(tg, "probe", ti, opts)
                rob.advance(sc.timing.compute_s)
                meas.append(None if det is None else _measure(det))
            sess.small_move(q_plan)
            if all(m is not None for m in meas):
                J = np.zeros((3, 3))
                for ax in range(3):
                    mp, mm = meas[1 + 2 * ax], meas[2 + 2 * ax]
                    assert mp is not None and mm is not None
                    J[:, ax] = (mp - mm) / (2 * h)
                jac[tid] = J
            sess.probes.append(
                {
                    "target": tid,
                    "touchup": ti,
                    "image_indices": p_imgs,
                    "base_image_index": p_imgs[0],
                    "shifts_m": [dv.tolist() for dv in shifts],
                    "shift_m": h,
                    "jacobian": jac[tid].tolist() if tid in jac else None,
                }
            )

        # ---- the closed loop
        if tid not in jac:
            lost = True
        else:
            J = jac[tid]
            for it in range(tt.max_iterations):
                iterations += 1
                idx = len(sess.images)
                det = sess.capture(tg, "loop", ti, opts, expected)
                if capture_mid:
                    fault_here.append(
                        {
                            "type": "capture_while_moving",
                            "phase": "approach",
                            "exposure_s": max(sc.camera.exposure_s, 0.04),
                            "renders": sess.last_renders,
                            "blur_px": [sess.images[idx]["blur_px"]],
                            "_images": [idx],
                        }
                    )
                    # let the interrupted move finish and settle
                    rob.advance(1.0)
                rob.advance(sc.timing.compute_s)
                if det is None:
                    lost = True
                    break
                expected = (det[0], det[1])
                e = _measure(det) - goal
                err_px = [det[0] - u0, det[1] - v0, det[2] - s0]
                final_err = [float(x) for x in err_px]
                if (
                    abs(err_px[0]) <= tt.threshold_px
                    and abs(err_px[1]) <= tt.threshold_px
                    and abs(err_px[2]) <= tt.threshold_size_px
                    and not capture_mid
                ):
                    converged = True
                    conv_images.append(idx)
                    break
                if it == tt.max_iterations - 1:
                    break
                dp = -gain * np.linalg.solve(J, e)
                q = sess.nominal_shift(q, dp)
                capture_mid = False
                sess.small_move(q)
            if converged:
                for _ in range(max(tt.repeat_captures - 1, 0)):
                    conv_images.append(len(sess.images))
                    sess.capture(tg, "extra", ti, opts, expected)
                    rob.advance(sc.timing.compute_s)
        opts.occluders = ()

        pin = sess.true_pin(q)
        tu_imgs = list(range(img_start, len(sess.images)))
        sess.touchups.append(
            {
                "index": ti,
                "target": tid,
                "label": labels[tid],
                "converged": converged,
                "lost": lost,
                "iterations": iterations,
                "gain": gain,
                "q": [float(x) for x in q],
                "image_indices": tu_imgs,
                "converged_image_indices": conv_images,
                "final_error_px": final_err,
                "target_centre": tg.centre.tolist(),
                "pin_miss_mm": ((pin - tg.centre) * 1000.0).tolist(),
                "in_file": True,
            }
        )
        for fh in fault_here:
            fh.setdefault("touchup", ti)
            if fh["type"] == "unconverged":
                fh["converged"] = converged
            if fh["type"] == "target_lost":
                fh["lost"] = lost
                fh["_images"] = tu_imgs[:1]
            fh.setdefault("_images", tu_imgs)
            sess.faults.append(fh)
        # (the knocked target's image indices are filled in below, once all are written)

    rob.advance(1.0)
    rec.flush(None)
    sess.safe_bytes = safe_bytes

    # image indices are known once written (log-time order)
    img_by_pos = sess.images
    order = sorted(range(len(img_by_pos)), key=lambda i: img_by_pos[i]["log_time_ns"])
    pos_to_index = {p: img_by_pos[p]["index"] for p in order}
    for tu in sess.touchups:
        tu["image_indices"] = [pos_to_index[p] for p in tu["image_indices"]]
        tu["converged_image_indices"] = [pos_to_index[p] for p in tu["converged_image_indices"]]
    for pr in sess.probes:
        pr["image_indices"] = [pos_to_index[p] for p in pr["image_indices"]]
        pr["base_image_index"] = pos_to_index[pr["base_image_index"]]
    tu_by_index = {tu["index"]: tu for tu in sess.touchups}
    for fl in sess.faults:
        if fl["type"] == "target_knocked":
            imgs = [i for k in fl["touchups_after"] for i in tu_by_index[k]["image_indices"]]
        elif fl["type"] == "joint_state_gap":
            continue
        else:
            imgs = [pos_to_index[p] for p in fl.pop("_images")]
        fl["image_indices"] = imgs
        fl["image_log_times_ns"] = [sess.images[_pos_of(sess, i)]["log_time_ns"] for i in imgs]
    sess.images.sort(key=lambda r: r["index"])

    return _truth(sess, plan, labels, known, metadata)


def _pos_of(sess: Session, index: int) -> int:
    for p, r in enumerate(sess.images):
        if r["index"] == index:
            return p
    raise KeyError(index)


def _truth(
    sess: Session,
    plan: list[tuple[int, F64]],
    labels: dict[int, int],
    known: list[dict[str, Any]],
    metadata: dict[str, str],
) -> dict[str, Any]:
    sc = sess.sc
    cell = sess.cell
    rob = sess.robot
    assert rob is not None
    cam = cell.camera
    return {
        "robot": sc.robot.name if not sc.robot.urdf else sc.robot.urdf,
        "seed": sess.seed,
        "scenario": sc.name,
        "faults_enabled": sc.faults.any(),
        "options": {
            "poses_per_target": sc.poses.per_target,
            "targets": sc.targets.count,
            "faults": sc.faults.any(),
            "polarity": sc.targets.polarity,
            "compressed": _image_encoding(sc) if sess.compressed else None,
            "known_distance": bool(known),
            "truncate_at": None,
            "scenario": sc.to_dict(),
        },
        "image_topic": sess.image_topic,
        "image_encoding": _image_encoding(sc),
        "metadata": metadata,
        "known_distances": known,
        "truncated": None,
        "joint_names": cell.nominal.joint_names,
        "base_link": sc.robot.base_link,
        "flange_link": sc.robot.flange_link,
        "nominal_urdf": cell.nominal_urdf,
        "true_urdf": cell.true_urdf,
        "true_urdf_with_pin": cell.true_urdf_with_pin,
        "deviations": cell.deviations,
        "camera": {
            "model": "pinhole, radial distortion x_d = x (1 + k1 r^2 + k2 r^4), OpenCV axes",
            **cam.to_dict(),
            "T_flange_camera": cell.T_flange_camera.tolist(),
        },
        "p_vt_flange": cell.p_vt_flange.tolist(),
        "p_vt_camera": cell.p_vt_camera.tolist(),
        "standoff_m": float(cell.p_vt_camera[2]),
        "designated": {"u": cell.u0, "v": cell.v0, "s0": cell.s0},
        "targets": [
            {
                "id": t.id,
                "label": labels.get(t.id),
                "centre": t.initial.tolist(),
                "normal": t.normal.tolist(),
                "diameter_m": sc.targets.diameter_m,
                "plate_radius_m": sc.targets.plate_radius_m,
                "history": [
                    {
                        "from_s": 0.0,
                        "from_ns": int(sc.timing.start_ns),
                        "centre": t.initial.tolist(),
                    }
                ]
                + t.history,
            }
            for t in cell.targets
        ],
        "touchups": sess.touchups,
        "probes": sess.probes,
        "images": sess.images,
        "counts": {
            "joint_states": rob.emitted,
            "images": len(sess.images),
            "touchups": len(sess.touchups),
        },
        "noise": {
            "encoder_rad": sc.timing.encoder_noise_rad,
            "image_grey_sigma": sc.camera.noise_sigma,
            "blur_sigma_px": sc.camera.blur_sigma_px,
            "vignetting": sc.camera.vignetting,
            "levels": {
                "target": float(sess.levels[0]),
                "plate": float(sess.levels[1]),
                "table": float(sess.background),
            },
        },
        "faults": sess.faults,
        "optics": sess.optics.truth() if sess.optics.active else None,
        "notes": NOTES,
    }


def _image_encoding(sc: Scenario) -> str:
    """What the image topic carries: ``jpeg``, ``png``, ``bgr8`` (Bayer, raw) or ``mono8``."""
    if sc.optics.jpeg_quality > 0:
        return "jpeg"
    if sc.camera.image == "png":
        return "png"
    return "bgr8" if sc.optics.bayer else "mono8"


def _truncate(
    path: Path, truth: dict[str, Any], rng: np.random.Generator, safe_bytes: int
) -> dict[str, Any]:
    """Cut the finished file inside the data of its last touch-up (the recorder was killed).

    ``safe_bytes`` is where the chunk before the last touch-up ended; the cut
    falls between it and the summary section, so every other fault's messages
    survive.

    What survives is found by streaming the cut file with the stock reader
    until it breaks; the images lost are listed as a ``truncated_file`` fault.
    """
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    size = path.stat().st_size
    with path.open("rb") as f:
        f.seek(size - 28)
        summary_start = int.from_bytes(f.read(8), "little") or size - 37
    cut = int(safe_bytes + rng.uniform(0.3, 0.8) * (summary_start - safe_bytes))
    os.truncate(path, cut)
    topics: dict[int, str] = {}
    kept: dict[str, int] = {}
    last_ns = 0
    with path.open("rb") as f:
        try:
            for r in StreamReader(f, skip_magic=False).records:
                if isinstance(r, Channel):
                    topics[r.id] = r.topic
                elif isinstance(r, Message):
                    t = topics.get(r.channel_id, "?")
                    kept[t] = kept.get(t, 0) + 1
                    last_ns = max(last_ns, r.log_time)
        except Exception:  # noqa: BLE001 - the reader breaks where the file was cut
            pass
    n_img = kept.get(truth["image_topic"], 0)
    lost = [im for im in truth["images"] if im["index"] >= n_img]
    for im in lost:
        im["in_file"] = False
    for tu in truth["touchups"]:
        tu["in_file"] = all(i < n_img for i in tu["image_indices"])
    truth["faults"].append(
        {
            "type": "truncated_file",
            "original_bytes": size,
            "kept_bytes": cut,
            "messages_kept": kept,
            "image_indices": [im["index"] for im in lost],
            "image_log_times_ns": [im["log_time_ns"] for im in lost],
        }
    )
    truth["options"]["truncate_at"] = cut
    return {
        "original_bytes": size,
        "kept_bytes": cut,
        "messages_kept": kept,
        "last_complete_log_time_ns": last_ns,
        "summary": False,
    }


def write_recording(
    sc: Scenario, seed: int, out: Path, progress: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Simulate and write ``out`` plus ``out.truth.json``; return the truth."""
    truth = simulate(sc, seed, out)
    tpath = Path(str(out) + ".truth.json")
    tmp = tpath.with_name(tpath.name + ".part")
    tmp.write_text(json.dumps(truth, indent=1))
    os.replace(tmp, tpath)
    return truth
