"""The simulated cell behind the measurement protocols: ``SimRobot``, ``SimCamera``, ``SimCell``.

The touch-up loop (:mod:`pipeline.live.loop`) drives the simulated session
(:mod:`pipeline.sim.session`) through these, exactly as it drives a live cell
through its adapter:

- :meth:`SimRobot.move_joints` is the large move (quintic, settle time after it);
- :meth:`SimRobot.move_flange` is the small move the simulated controller makes
  with its *nominal* kinematics: ``T_base_flange <- T_base_flange Trans(dp)``
  solved by nominal IK from the commanded joints (the true flange moves by a
  slightly different amount: the robot is not the nominal one);
- :meth:`SimRobot.read_joints` reads the commanded joint angles noise-free (the
  recorded ``/joint_states`` add encoder noise); :meth:`SimRobot.is_still` is
  true once the last move ended and the settle time passed; :meth:`SimRobot.wait`
  advances the session clock (streaming joint states);
- :meth:`SimCamera.capture` renders the target in view, records the image and
  returns it as a :class:`~pipeline.live.protocols.Frame`.

Two fault hooks serve the simulator (the loop knows nothing of them):
``SimRobot.stop_next_move`` makes the next large move return at a fraction of its
duration with the controller claiming stillness once (a capture while moving),
and ``SimCamera.target`` / ``SimCamera.options`` pick the rendered target and
add second blobs or occluders.

:meth:`SimCell.from_scenario` builds the whole cell from a scenario and a seed,
recording into a :class:`~pipeline.io.mcap_write.Recorder` or nowhere (a cell run
standalone, e.g. behind the TCP reference server).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from pipeline.io.mcap_write import NullRecorder, Recorder
from pipeline.kinematics.se3 import F64
from pipeline.live.loop import Detection, Detector, Goal, LoopConfig
from pipeline.live.protocols import Frame, JointReading
from pipeline.sim.cell import Target, known_distances, touchup_metadata
from pipeline.sim.detect import detect_target
from pipeline.sim.poses import measuring_poses
from pipeline.sim.scenario import Scenario
from pipeline.sim.session import CaptureOptions, JointStream, Session


class SimRobot:
    """:class:`~pipeline.live.protocols.Robot` on a simulated session."""

    def __init__(self, sess: Session) -> None:
        self.sess = sess
        #: fault hook: ``(fraction, target)``: the next large move returns at about this
        #: share of its duration (blurring ``target``) and is reported still once
        self.stop_next_move: tuple[float, Target] | None = None
        self._claim_still = 0

    @property
    def arm(self) -> JointStream:
        rob = self.sess.robot
        assert rob is not None
        return rob

    @property
    def joint_names(self) -> list[str]:
        return list(self.sess.cell.nominal.joint_names)

    def read_joints(self) -> JointReading:
        arm = self.arm
        q = arm.goal if arm.settled(0.0) else arm.q_at(arm.t)
        return JointReading(np.array(q, dtype=float), int(arm.t))

    def move_joints(self, q: F64, speed: float = 1.0) -> None:
        q = np.asarray(q, dtype=float)
        if self.stop_next_move is not None:
            frac, tg = self.stop_next_move
            self.stop_next_move = None
            self._claim_still = 1
            self.sess.large_move(q, stop_at=frac, tg=tg, speed=speed)
            return
        self.sess.large_move(q, speed=speed)

    def move_flange(self, dp_flange_m: F64) -> None:
        q = self.sess.nominal_shift(self.arm.goal, np.asarray(dp_flange_m, dtype=float))
        self.sess.small_move(q)

    def is_still(self) -> bool:
        if self._claim_still > 0:
            self._claim_still -= 1
            return True
        return self.arm.settled(self.sess.sc.timing.settle_s)

    def wait(self, seconds: float) -> None:
        self.arm.advance(seconds)


class SimCamera:
    """:class:`~pipeline.live.protocols.Camera` on a simulated session.

    ``target`` is the target rendered (None: the one nearest the optical axis);
    ``options`` adds second blobs or occluders (fault injection).
    """

    def __init__(self, sess: Session) -> None:
        self.sess = sess
        self.target: Target | None = None
        self.options = CaptureOptions()
        self._grey: tuple[int, np.ndarray] | None = None

    def target_in_view(self) -> Target:
        """The target nearest the optical axis, in front of the camera, at the current pose."""
        arm = self.sess.robot
        assert arm is not None
        q = arm.q_at(arm.t)

        def off_axis(tg: Target) -> float:
            p = self.sess.camera_target(q, tg)[:3, 3]
            return float(np.hypot(p[0], p[1]) / p[2]) if p[2] > 0 else np.inf

        return min(self.sess.cell.targets, key=off_axis)

    def capture(self) -> Frame:
        """The image as the camera delivers it: a JPEG camera's (``[optics] jpeg_quality``)
        decoded from its JPEG bytes, as a client of a JPEG stream sees it."""
        tg = self.target if self.target is not None else self.target_in_view()
        img, grey, stamp_ns = self.sess.capture(tg, self.options)
        self._grey = (stamp_ns, grey)
        if self.sess.sc.optics.jpeg_quality > 0:
            _, data = self.sess.optics.encode(img)
            img = np.asarray(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED))
        return Frame(img, stamp_ns, "bgr8" if img.ndim == 3 else "mono8")

    def grey_of(self, frame: Frame) -> np.ndarray:
        """The grey image the simulated sensor made of ``frame`` (the last one captured)."""
        if self._grey is None or self._grey[0] != frame.stamp_ns:
            raise ValueError(f"frame {frame.stamp_ns} is not the last capture")
        return self._grey[1]


def controller_detector(camera: SimCamera, goal: Goal, method: str) -> Detector:
    """The simulated controller's own detector (:mod:`pipeline.sim.detect`) as a loop
    :data:`~pipeline.live.loop.Detector`: a model of a cell's recorder, deliberately
    independent of vtcal's detection."""

    def detect(frame: Frame, expected_uv: tuple[float, float] | None) -> Detection:
        return detect_target(
            camera.grey_of(frame),
            goal.polarity,
            expected_uv=expected_uv or (goal.u0, goal.v0),
            method=method,
        )

    return detect


def camera_response_of(kind: str, gamma: float) -> str | None:
    """The spec's ``camera_response`` (``recording.md``) of a scenario's ``[optics] response``.

    ``linear`` and ``srgb`` as they are, ``gamma`` as ``gamma:G``; None for ``curve``
    (an unnamed monotone curve).
    """
    if kind in ("linear", "srgb"):
        return kind
    if kind == "gamma":
        return f"gamma:{gamma:g}"
    return None


@dataclass
class SimCell:
    """A simulated cell ready to be measured: protocol objects, the nominal URDF, the plan.

    Attributes
    ----------
    sess : Session
    robot : SimRobot
    camera : SimCamera
    plan : list of (target_id, (n,) q)
        The scenario's measuring poses, in order.
    labels : dict
        Target id -> label (order of first touch-up, spec ``recording.md``).
    known : list of dict
        The calibration bar's known distance(s).
    metadata : dict
        The recording's ``touchup`` metadata record.
    goal : Goal
        Designated values and thresholds.
    """

    sess: Session
    robot: SimRobot
    camera: SimCamera
    plan: list[tuple[int, F64]]
    labels: dict[int, int]
    known: list[dict[str, Any]]
    metadata: dict[str, str]
    goal: Goal

    @property
    def nominal_urdf(self) -> str:
        return self.sess.cell.nominal_urdf

    @property
    def served_metadata(self) -> dict[str, str]:
        """The ``touchup`` keys the cell serves to a client (``META?``; the ``sim:`` link).

        The recorded :attr:`metadata` plus what the cell knows of itself that its own
        recordings leave to be estimated: ``camera_response``, the encoding its camera
        applies (``linear``, ``srgb``, ``gamma:G``; none for a ``curve``, which the
        spec's key cannot name).
        """
        out = dict(self.metadata)
        response = camera_response_of(self.sess.sc.optics.response, self.sess.sc.optics.gamma)
        if response is not None:
            out["camera_response"] = response
        return out

    @classmethod
    def from_scenario(cls, sc: Scenario, seed: int, rec: Recorder | None = None) -> SimCell:
        """Draw the cell of ``sc`` and ``seed``, plan its poses, start its clock at home.

        With ``rec`` the recording starts: the nominal URDF on ``/robot_description``
        and the ``touchup`` metadata record, then joint states (one second at home).
        Without, nothing is recorded (the client of an adapter records).
        """
        sess = Session(sc, seed, rec if rec is not None else NullRecorder())
        cell = sess.cell
        plan = measuring_poses(sc, cell, sess.rng_pose)
        labels: dict[int, int] = {}
        for tid, _ in plan:
            labels.setdefault(tid, len(labels))
        known = known_distances(sc, cell, labels)
        metadata = touchup_metadata(sc, cell, known)
        t0 = sc.timing.start_ns
        sess.rec.push(t0, "/robot_description", "std_msgs/msg/String", {"data": cell.nominal_urdf})
        sess.rec.flush(t0)
        sess.rec.metadata("touchup", metadata)
        sess.robot = JointStream(
            sess.rec,
            cell.nominal.joint_names,
            cell.home,
            t0,
            sc.timing.joint_rate_hz,
            sc.timing.encoder_noise_rad,
            sess.rng_enc,
        )
        sess.robot.advance(1.0)
        tt = sc.touchup
        goal = Goal(
            cell.u0, cell.v0, cell.s0, tt.threshold_px, tt.threshold_size_px, sc.targets.polarity
        )
        return cls(sess, SimRobot(sess), SimCamera(sess), plan, labels, known, metadata, goal)

    def loop_config(self) -> LoopConfig:
        """The scenario's touch-up settings as a loop configuration (the paper's loop: one
        probed Jacobian per target, not updated)."""
        sc = self.sess.sc
        tt = sc.touchup
        return LoopConfig(
            gain=tt.gain,
            max_iterations=tt.max_iterations,
            repeat_captures=tt.repeat_captures,
            probe_shift_m=tt.probe_shift_m,
            compute_s=sc.timing.compute_s,
            update_jacobian=False,
        )

    def detector(self) -> Detector:
        """The simulated controller's detector (scenario ``[touchup] controller``)."""
        return controller_detector(self.camera, self.goal, self.sess.sc.touchup.controller)
