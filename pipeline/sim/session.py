"""The simulated session's clock, motion and camera: joint-state stream, moves, captures.

:class:`JointStream` is the arm's commanded motion on the session clock, streamed
as ``/joint_states``; :class:`Session` holds the world (:mod:`pipeline.sim.cell`),
the recorder and the truth lists, moves the arm (nominal IK for flange moves)
and renders, encodes and records each capture. The touch-up loop drives it
through :mod:`pipeline.sim.cell_adapter`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.io.mcap_write import Recorder, stamp
from pipeline.kinematics.chain import fk
from pipeline.kinematics.se3 import F64, invert_transform, matrix_from_axis_angle, translation
from pipeline.sim.cell import Target, build_cell
from pipeline.sim.image_finish import Occluder, finish_image, paint_occluders
from pipeline.sim.optics_state import OpticsState
from pipeline.sim.render import ExtraDisc, render_ideal
from pipeline.sim.robot import solve_ik
from pipeline.sim.scenario import Scenario
from pipeline.sim.target_geometry import projected_ellipse

NS = 1_000_000_000
JOINT_LATENCY_NS = 2_000_000


class JointStream:
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

    def settled(self, settle_s: float) -> bool:
        """The current move ended at least ``settle_s`` ago (1 us of clock rounding allowed)."""
        _, _, ts, dur = self.seg
        return self.t >= ts + dur + int(settle_s * NS) - 1000

    @property
    def goal(self) -> F64:
        """Joint vector the current (or last) move goes to."""
        return self.seg[1]

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


#: An alternative image source: ``(target, Ts (K, 4, 4) T_camera_target over the exposure,
#: options) -> (image, grey)`` as :meth:`Session.capture` returns them (e.g.
#: :class:`pipeline.sim.render_pbr.PbrSource`); None: the simulator's own renderer.
ImageSource = Callable[[Target, F64, CaptureOptions], tuple[np.ndarray, np.ndarray]]


class Session:
    """One simulated calibration session (the controller + the world + the recorder)."""

    def __init__(self, sc: Scenario, seed: int, rec: Recorder) -> None:
        self.sc = sc
        self.seed = seed
        ss = np.random.SeedSequence(seed)
        streams = ss.spawn(6)
        cell_stream = streams[0]
        if sc.robot.cell_seed >= 0:  # the robot of cell_seed, re-recorded with this seed
            cell_stream = np.random.SeedSequence(sc.robot.cell_seed).spawn(6)[0]
        self.rng_cell = np.random.default_rng(cell_stream)
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
        self.robot: JointStream | None = None
        #: forms each capture instead of :meth:`_form_image` when set
        self.image_source: ImageSource | None = None
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

    def camera_target(self, q: F64, tg: Target) -> F64:
        """``T_camera_target`` (4, 4) at joints ``q`` on the true chain."""
        T_base_cam = fk(self.cell.true, q) @ self.cell.T_flange_camera
        return invert_transform(T_base_cam) @ tg.T_base_target()

    def true_pin(self, q: F64) -> F64:
        T = fk(self.cell.true, q)
        return T[:3, :3] @ self.cell.p_vt_flange + T[:3, 3]

    def capture(
        self, tg: Target, opts: CaptureOptions | None = None
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Expose, render, encode and queue one image of target ``tg``.

        Appends the image's truth record to :attr:`images` (its ``kind``,
        ``touchup`` and ``sim_detection`` are filled by whoever runs the loop)
        and lets the exposure time pass.

        Returns
        -------
        image : (H, W) uint8 or (H, W, 3) uint8 (Bayer-demosaiced BGR)
            What the camera delivers (and the recording carries).
        grey : (H, W) uint8
            What the simulated controller's detector sees.
        stamp_ns : int
            Middle of the exposure.
        """
        rob = self.robot
        assert rob is not None
        opts = opts or CaptureOptions()
        t_start = rob.t
        exp_ns, moving, Ts = self._exposure(tg, t_start)
        form = self.image_source or self._form_image
        img, grey = form(tg, Ts, opts)
        rec = self._image_record(tg, opts, t_start, exp_ns, moving, Ts)
        self.last_renders = len(Ts)
        self.images.append(rec)
        msg, datatype = self._image_message(img, rec["stamp_ns"])

        def on_write(idx: int, seq: int, rec: dict[str, Any] = rec) -> None:
            rec["index"] = idx
            rec["mcap_sequence"] = seq

        self.rec.push(rec["log_time_ns"], self.image_topic, datatype, msg, on_write)
        rob.advance(exp_ns / NS)
        return img, grey, int(rec["stamp_ns"])

    def _exposure(self, tg: Target, t_start: int) -> tuple[int, bool, F64]:
        """The exposure starting at ``t_start`` (ns): its length (ns), whether the arm moves
        during it, and ``T_camera_target`` ``(n_sub, 4, 4)`` at the middle of each of its
        ``n_sub`` sub-exposures (one when still, 3 while the camera vibrates, 5 to 40 when
        moving: enough that consecutive copies are < 0.5 px apart)."""
        rob = self.robot
        assert rob is not None
        sc = self.sc
        exp_ns = int(sc.camera.exposure_s * NS)
        moving = rob.moving_at(t_start) or rob.moving_at(t_start + exp_ns)
        if moving:
            exp_ns = int(max(sc.camera.exposure_s, 0.04) * NS)
        n_sub = 1
        op = self.optics
        if moving:
            # enough sub-exposure renders that consecutive copies are < 0.5 px apart
            ends = [self.camera_target(rob.q_at(t), tg) for t in (t_start, t_start + exp_ns)]
            sweep = float(np.linalg.norm(cam_project(self, ends[1]) - cam_project(self, ends[0])))
            n_sub = int(np.clip(np.ceil(sweep / 0.5), 5, 40))
        elif op.vibration.active:
            n_sub = 3  # the camera still shakes during the exposure
        times = [t_start + exp_ns * (k + 0.5) / n_sub for k in range(n_sub)]
        qs = [rob.q_at(t) for t in times]
        Ts = np.stack(
            [op.shaken(self.camera_target(q, tg), t) for q, t in zip(qs, times, strict=True)]
        )
        return exp_ns, bool(moving), Ts

    def _form_image(
        self, tg: Target, Ts: F64, opts: CaptureOptions
    ) -> tuple[np.ndarray, np.ndarray]:
        """Render target ``tg`` over the sub-exposure poses ``Ts`` and form the image:
        ``(image, grey)`` as :meth:`capture` returns them."""
        sc = self.sc
        op = self.optics
        cam = self.cell.camera
        ideal = render_ideal(
            cam,
            Ts,
            sc.targets.diameter_m,
            levels=self.levels,
            plate_radius_m=sc.targets.plate_radius_m,
            background_grey=self.background,
            extra_discs=opts.extra_discs,
            subsamples=sc.camera.subsamples,
            blur_sigma_px=sc.camera.blur_sigma_px,
            target_shape=op.shapes.get(tg.id),
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
        return img, grey

    def _image_record(
        self,
        tg: Target,
        opts: CaptureOptions,
        t_start: int,
        exp_ns: int,
        moving: bool,
        Ts: F64,
    ) -> dict[str, Any]:
        """The truth record of the image exposed from ``t_start`` for ``exp_ns`` (stamped at
        the middle of the exposure): the exact projected ellipse there, the blur of a moving
        capture (centre sweep over the exposure, px)."""
        rob = self.robot
        assert rob is not None
        sc = self.sc
        cam = self.cell.camera
        op = self.optics
        n_sub = len(Ts)
        t_mid = t_start + exp_ns // 2
        q_mid = rob.q_at(t_mid)
        T_mid = op.shaken(self.camera_target(q_mid, tg), t_mid)
        centre_px = cam.project(T_mid[:3, 3])
        ell = projected_ellipse(cam, T_mid, sc.targets.diameter_m, shape=op.shapes.get(tg.id))
        blur_px = 0.0
        if moving:
            c = np.array([cam.project(T[:3, 3]) for T in Ts])
            blur_px = float(np.linalg.norm(c[-1] - c[0]) * n_sub / max(n_sub - 1, 1))
        stamp_ns = t_mid
        log_ns = t_start + exp_ns + int(sc.camera.latency_s * NS)
        return {
            "index": -1,
            "stamp_s": (stamp_ns - rob.t0) / NS,
            "log_s": (log_ns - rob.t0) / NS,
            "kind": "",
            "touchup": -1,
            "target": tg.id,
            "moving": bool(moving),
            "screw": False,
            "occluded": bool(opts.occluders),
            "second_blob": bool(opts.extra_discs),
            "visible_fraction": 0.0 if opts.occluders else 1.0,
            "q_true": [float(x) for x in q_mid],
            "sim_detection": None,
            "sim_detection_cut": False,
            "true_centre_px": [float(x) for x in centre_px],
            "true_ellipse": [float(x) for x in ell],
            "blur_px": blur_px,
            "mcap_sequence": -1,
            "in_file": True,
            "log_time_ns": int(log_ns),
            "stamp_ns": int(stamp_ns),
        }

    def _image_message(self, img: np.ndarray, stamp_ns: int) -> tuple[dict[str, Any], str]:
        """The ROS 2 message of ``img`` (compressed, or raw ``mono8``/``bgr8``) and its type."""
        cam = self.cell.camera
        header = {"stamp": stamp(stamp_ns), "frame_id": "camera_optical_frame"}
        msg: dict[str, Any]
        if self.compressed:
            fmt, data = self.optics.encode(img)
            msg = {"header": header, "format": fmt, "data": data}
            return msg, "sensor_msgs/msg/CompressedImage"
        colour = img.ndim == 3
        msg = {
            "header": header,
            "height": cam.height,
            "width": cam.width,
            "encoding": "bgr8" if colour else "mono8",
            "is_bigendian": 0,
            "step": cam.width * (3 if colour else 1),
            "data": np.ascontiguousarray(img).tobytes(),
        }
        return msg, "sensor_msgs/msg/Image"

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
            a = cam_project(self, self.camera_target(rob.q_at(ta), tg))
            b = cam_project(self, self.camera_target(rob.q_at(ta + exp_ns), tg))
            if np.linalg.norm(b - a) >= want_px:
                return float(frac)
        return 0.3

    def large_move(
        self,
        q_goal: F64,
        stop_at: float | None = None,
        tg: Target | None = None,
        speed: float = 1.0,
    ) -> None:
        """Move to ``q_goal`` at ``speed`` (share of the scenario's top joint speed) and
        settle; with ``stop_at`` return mid-move (blurred capture)."""
        rob = self.robot
        assert rob is not None
        dur = rob.move_duration(q_goal, self.sc.timing.max_speed_rad_s * speed, 0.8)
        rob.start_move(q_goal, dur)
        self.optics.on_move(rob.t + dur * NS)
        if stop_at is not None and tg is not None:
            rob.advance(self._blur_fraction(tg, dur, stop_at) * dur)
            return
        rob.advance(dur + self.sc.timing.settle_s)


def cam_project(sess: Session, T_camera_target: F64) -> F64:
    """Pixel of the target centre (for blur estimates)."""
    return sess.cell.camera.project(T_camera_target[:3, 3])
