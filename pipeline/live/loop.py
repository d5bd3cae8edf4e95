"""The visual touch-up loop (paper sec. 2.1; spec ``recording.md``), one implementation.

A client (the simulator's recorder, ``vtcal measure``, a test) moves the arm to a
planned pose with :meth:`Robot.move_joints`, then calls

1. :func:`estimate_jacobian` (once per target, or once per run): the image
   Jacobian ``J = d(u, v, 1/s) / d(p_flange)`` from small flange shifts;
2. :func:`touch_up`: capture -> ``e_T`` -> flange step ``-gain J^-1 e_T`` until
   every component of the error is under its threshold.

The loop sees the cell only through the protocols of
:mod:`pipeline.live.protocols`, sees the image only through a
:data:`Detector`, and hands every captured frame to an :data:`OnCapture`
callback (the client records it). It holds no state between calls: what it
learns (the Jacobian) comes back in the result.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.live.protocols import F64, Camera, Frame, JointReading, Robot
from pipeline.measurement.image import image_error
from pipeline.measurement.image_jacobian import fit_image_jacobian, servo_step

#: ``(u, v, s)``: target centre and full long axis of its ellipse (px), or None (not found)
Detection = tuple[float, float, float] | None
#: ``detect(frame, expected_uv) -> Detection``; ``expected_uv`` is where the target
#: was last seen (the designated pixel before the first detection)
Detector = Callable[[Frame, "tuple[float, float] | None"], Detection]

#: why a touch-up ended (:attr:`TouchupResult.reason`)
REASONS = ("converged", "lost_target", "border", "iteration_limit", "no_jacobian")
#: what a capture was for (:attr:`CaptureInfo.kind`)
CAPTURE_KINDS = ("probe", "loop", "extra")


@dataclass(frozen=True)
class Goal:
    """Where the target is driven to in the image and when it is there (spec ``recording.md``).

    Attributes
    ----------
    u0, v0 : float
        Designated centre (px; ``(0, 0)`` is the centre of the top-left pixel).
    s0 : float
        Designated full long axis (px).
    threshold_px, threshold_size_px : float
        Convergence thresholds on the centre and on the long axis (px).
    polarity : str
        ``dark_on_light`` or ``light_on_dark`` (for the detector).
    """

    u0: float
    v0: float
    s0: float
    threshold_px: float
    threshold_size_px: float
    polarity: str

    def error(self, det: tuple[float, float, float]) -> F64:
        """``e_T = (u - u0, v - v0, 1/s - 1/s0)`` (px, px, 1/px), shape (3,)
        (:func:`pipeline.measurement.image.image_error`)."""
        return image_error(det[0], det[1], det[2], self.u0, self.v0, self.s0)

    def error_px(self, det: tuple[float, float, float]) -> tuple[float, float, float]:
        """``(u - u0, v - v0, s - s0)`` in px: what the convergence test compares."""
        return (float(det[0] - self.u0), float(det[1] - self.v0), float(det[2] - self.s0))

    def reached(self, det: tuple[float, float, float]) -> bool:
        """Convergence per component: ``|u - u0|, |v - v0| <= threshold_px`` and
        ``|s - s0| <= threshold_size_px``."""
        du, dv, ds = self.error_px(det)
        return (
            abs(du) <= self.threshold_px
            and abs(dv) <= self.threshold_px
            and abs(ds) <= self.threshold_size_px
        )


@dataclass(frozen=True)
class LoopConfig:
    """Settings of the loop.

    Attributes
    ----------
    gain : float
        Fraction of the linear correction applied per step (``0 < gain <= 1``).
    max_iterations : int
        Captures of the loop proper before it gives up (``iteration_limit``).
    repeat_captures : int
        Still captures at the converged pose (the converging one included).
    probe_shift_m : float
        ``h`` of the probing shifts ``+-h`` along each flange axis.
    max_step_m : float
        Longest servo step; a longer one is shortened along its own direction.
    still_timeout_s : float
        How long to wait for :meth:`Robot.is_still` before capturing anyway (the
        capture is then flagged not still and cannot converge).
    still_poll_s : float
        Cell time between two stillness queries.
    compute_s : float
        Cell time let pass after each capture (a simulated controller's processing
        time; 0 on a live cell, whose processing takes real time already).
    update_jacobian : bool
        Re-estimate the Jacobian from the loop's own steps (:func:`broyden_update`).
    update_min_step_m : float
        Steps shorter than this do not update the Jacobian (their image change is
        mostly detection noise).
    border_margin_px : float
        A detection whose long-axis circle reaches within this of the image edge
        is cut by the border: the touch-up gives up (``border``).
    """

    gain: float = 0.9
    max_iterations: int = 12
    repeat_captures: int = 3
    probe_shift_m: float = 0.002
    max_step_m: float = 0.05
    still_timeout_s: float = 5.0
    still_poll_s: float = 0.05
    compute_s: float = 0.0
    update_jacobian: bool = False
    update_min_step_m: float = 2e-4
    border_margin_px: float = 0.0


@dataclass(frozen=True)
class CaptureInfo:
    """What the loop knows of one captured frame (handed to :data:`OnCapture`).

    Attributes
    ----------
    kind : str
        ``probe`` (Jacobian probing), ``loop`` (a servo iteration) or ``extra``
        (a repeat capture at convergence).
    touchup : int
        The client's touch-up index.
    stamp_ns : int
        The frame's stamp (middle of exposure).
    detection : Detection
    still : bool
        The robot reported still before and after the exposure.
    """

    kind: str
    touchup: int
    stamp_ns: int
    detection: Detection
    still: bool


#: ``on_capture(frame, info)``: called once per captured frame, after detection
OnCapture = Callable[[Frame, CaptureInfo], None]


@dataclass
class TouchupResult:
    """The outcome of :func:`touch_up`.

    Attributes
    ----------
    converged : bool
    lost : bool
        The target was lost or cut by the border (reason ``lost_target``,
        ``border`` or ``no_jacobian``).
    reason : str
        One of :data:`REASONS`.
    iterations : int
        Loop captures taken (extras not counted).
    final_error_px : (u - u0, v - v0, s - s0) or None
        Of the last detection.
    joints : JointReading
        ``robot.read_joints()`` at the end (the converged pose when converged).
    captures : list of CaptureInfo
    jacobian : (3, 3) float64 or None
        The Jacobian the loop ended with (updated when ``update_jacobian``).
    """

    converged: bool
    lost: bool
    reason: str
    iterations: int
    final_error_px: tuple[float, float, float] | None
    joints: JointReading
    captures: list[CaptureInfo] = field(default_factory=list)
    jacobian: F64 | None = None


def wait_still(robot: Robot, cfg: LoopConfig) -> bool:
    """Poll :meth:`Robot.is_still` every ``still_poll_s`` up to ``still_timeout_s``."""
    waited = 0.0
    while not robot.is_still():
        if waited >= cfg.still_timeout_s:
            return False
        robot.wait(cfg.still_poll_s)
        waited += cfg.still_poll_s
    return True


def capture(
    robot: Robot,
    camera: Camera,
    detect: Detector,
    on_capture: OnCapture,
    kind: str,
    touchup: int,
    expected_uv: tuple[float, float] | None,
    cfg: LoopConfig,
) -> tuple[Frame, CaptureInfo]:
    """One still capture: wait for stillness, expose, detect, report, let ``compute_s`` pass.

    The capture counts as still when the robot says so before and after the
    exposure (a controller that reports stillness too early is caught by the
    second query). Returns the frame and what the loop made of it.
    """
    still = wait_still(robot, cfg)
    frame = camera.capture()
    still = still and robot.is_still()
    det = detect(frame, expected_uv)
    info = CaptureInfo(kind, touchup, int(frame.stamp_ns), det, still)
    on_capture(frame, info)
    if cfg.compute_s > 0:
        robot.wait(cfg.compute_s)
    return frame, info


def probe_shifts(h: float) -> list[F64]:
    """The probing poses relative to the base pose: ``0, +h x, -h x, +h y, -h y, +h z, -h z``."""
    out = [np.zeros(3)]
    for ax in range(3):
        for sgn in (1.0, -1.0):
            d = np.zeros(3)
            d[ax] = sgn * h
            out.append(d)
    return out


def jacobian_from_probes(meas: list[F64], h: float) -> F64 | None:
    """The image Jacobian from the probe measurements, by the one estimator (J1).

    ``meas`` in the order of :func:`probe_shifts` (``meas[0]`` the base capture): the
    pairs ``(d_k, m_k - m_0)`` of the six shifts go to
    :func:`pipeline.measurement.image_jacobian.fit_image_jacobian`, where symmetric
    axis-aligned pairs make each column the central difference
    ``(m(+h e_k) - m(-h e_k)) / (2 h)`` (paper sec. 2.1; truncation ``O(h^2)``).

    Parameters
    ----------
    meas : list of 7 (3,) arrays ``m = (u, v, 1/s)``
    h : float
        Shift (m).

    Returns
    -------
    (3, 3) ``J = d(u, v, 1/s) / d(p_flange)`` (px/m, px/m, 1/(px m)), or None if
    ill-posed.
    """
    dF = np.array(probe_shifts(h)[1:])
    dm = np.array(meas[1:]) - np.asarray(meas[0])[None, :]
    return fit_image_jacobian(dF, dm, min_pairs=len(dF))


def estimate_jacobian(
    robot: Robot,
    camera: Camera,
    detect: Detector,
    on_capture: OnCapture,
    goal: Goal,
    cfg: LoopConfig,
    touchup: int,
) -> F64 | None:
    """Probe the image Jacobian at the current pose (paper sec. 2.1) and return to it.

    A capture at the base pose and after each flange shift of
    :func:`probe_shifts` (each shift is reached from the previous one by a pure
    flange translation, ``move_flange(d_k - d_{k-1})``); then back to the base
    pose. ``J`` by :func:`jacobian_from_probes`.

    Returns
    -------
    (3, 3) ``J = d(u, v, 1/s) / d(p_flange)``, or None when the target was not
    found in one of the captures (or the shifts were ill-posed).
    """
    h = cfg.probe_shift_m
    at = np.zeros(3)
    meas: list[F64 | None] = []
    for d in probe_shifts(h):
        if np.any(d != at):
            robot.move_flange(d - at)
            at = d
        _, info = capture(
            robot, camera, detect, on_capture, "probe", touchup, (goal.u0, goal.v0), cfg
        )
        det = info.detection
        meas.append(None if det is None else np.array([det[0], det[1], 1.0 / det[2]]))
    robot.move_flange(-at)
    if any(m is None for m in meas):
        return None
    return jacobian_from_probes([m for m in meas if m is not None], h)


def broyden_update(J: F64, dp: F64, de: F64) -> F64:
    """Good Broyden rank-one update of the image Jacobian from one servo step.

    Each step moves the flange by a known small pure translation ``dp`` between
    two still captures and measures the change ``de`` of ``(u, v, 1/s)``: the pair
    the spec (``recording.md``) lets a pipeline use as a probe. The update is the
    smallest change of ``J`` (Frobenius norm) that satisfies the secant
    condition ``J+ dp = de``:

        J+ = J + (de - J dp) dp^T / (dp^T dp)

    (Broyden 1965; Dennis & Schnabel, *Numerical Methods for Unconstrained
    Optimization*, sec. 8.1). Directions orthogonal to ``dp`` keep what the
    probing measured; along ``dp`` the loop's own motion replaces it, so a
    Jacobian that drifts as the arm reorients (or started wrong) is corrected
    by the moves the loop makes anyway, without extra probing moves.

    Parameters
    ----------
    J : (3, 3)
    dp : (3,) flange step (m)
    de : (3,) measured change of ``(u, v, 1/s)``

    Returns
    -------
    (3, 3) updated ``J``.
    """
    out: F64 = J + np.outer(de - J @ dp, dp) / float(dp @ dp)
    return out


def at_border(det: tuple[float, float, float], width: int, height: int, margin: float) -> bool:
    """The circle of diameter ``s`` about ``(u, v)`` reaches within ``margin`` px of the edge
    (pixel centres at integers: the image spans ``[-0.5, W - 0.5]``)."""
    u, v, s = det
    r = 0.5 * s + margin
    return u - r < -0.5 or v - r < -0.5 or u + r > width - 0.5 or v + r > height - 0.5


def touch_up(
    robot: Robot,
    camera: Camera,
    detect: Detector,
    on_capture: OnCapture,
    goal: Goal,
    cfg: LoopConfig,
    jacobian: F64 | None,
    touchup: int,
) -> TouchupResult:
    """Servo the target to the goal from the current pose (spec ``recording.md``, step 2).

    Per iteration (at most ``max_iterations``): a still capture (:func:`capture`),
    ``e_T = (u - u0, v - v0, 1/s - 1/s0)``, then

    - **converged** when the capture was still and ``|u - u0|, |v - v0| <=
      threshold_px`` and ``|s - s0| <= threshold_size_px``; ``repeat_captures - 1``
      extra still captures follow at that pose;
    - **lost_target** when the detector finds nothing; **border** when the
      target's circle reaches the image edge (:func:`at_border`);
    - **iteration_limit** when the last allowed capture has not converged;
    - otherwise the step :func:`servo_step` ``dp = -gain J^-1 e_T`` (clipped to
      ``max_step_m``) by :meth:`Robot.move_flange`; with ``update_jacobian`` the
      next still capture updates ``J`` by :func:`broyden_update` with that step
      (steps shorter than ``update_min_step_m`` are skipped).

    With no Jacobian (probing failed) nothing is captured: reason ``no_jacobian``.
    """
    caps: list[CaptureInfo] = []

    def record(frame: Frame, info: CaptureInfo) -> None:
        caps.append(info)
        on_capture(frame, info)

    if jacobian is None:
        return TouchupResult(False, True, "no_jacobian", 0, None, robot.read_joints(), caps, None)
    J = np.array(jacobian, dtype=float)
    expected = (goal.u0, goal.v0)
    final: tuple[float, float, float] | None = None
    reason = "iteration_limit"
    last: tuple[F64, F64] | None = None  # (measurement, step taken after it)
    iterations = 0
    for it in range(cfg.max_iterations):
        iterations += 1
        frame, info = capture(robot, camera, detect, record, "loop", touchup, expected, cfg)
        det = info.detection
        if det is None:
            reason = "lost_target"
            break
        final = goal.error_px(det)
        height, width = frame.image.shape[:2]
        if at_border(det, width, height, cfg.border_margin_px):
            reason = "border"
            break
        expected = (det[0], det[1])
        m = np.array([det[0], det[1], 1.0 / det[2]])
        if cfg.update_jacobian and last is not None and info.still:
            m_prev, dp_prev = last
            if float(np.linalg.norm(dp_prev)) >= cfg.update_min_step_m:
                J = broyden_update(J, dp_prev, m - m_prev)
        if info.still and goal.reached(det):
            reason = "converged"
            break
        if it == cfg.max_iterations - 1:
            break
        dp = servo_step(J, goal.error(det), cfg.gain, cfg.max_step_m)
        robot.move_flange(dp)
        last = (m, dp) if info.still else None
    if reason == "converged":
        for _ in range(max(cfg.repeat_captures - 1, 0)):
            capture(robot, camera, detect, record, "extra", touchup, expected, cfg)
    return TouchupResult(
        converged=reason == "converged",
        lost=reason in ("lost_target", "border"),
        reason=reason,
        iterations=iterations,
        final_error_px=final,
        joints=robot.read_joints(),
        captures=caps,
        jacobian=J,
    )
