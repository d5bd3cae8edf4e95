"""The simulated touch-up cell: a true robot, a camera, targets, a controller, a recorder.

:func:`simulate` runs one calibration session as the paper describes it and
streams what a real cell would record (``spec/recording.md``) into an
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
    vtcal's own touch-up loop (:mod:`pipeline.live.loop`, the one a live
    cell runs), driving the session through the cell adapter
    (:mod:`pipeline.sim.cell_adapter`): the *nominal* chain for every flange
    motion (nominal IK) and the simulated controller's own detection of
    ``(u, v, s)`` on each rendered image (:mod:`pipeline.sim.detect`, a model of
    a recorder's simpler detector, independent of vtcal's). Per target it first
    probes the image Jacobian ``J = d(u, v, 1/s) / d(p_flange)`` by
    +-``probe_shift_m`` flange shifts (central differences), then runs

        e_T = (u - u0, v - v0, 1/s - 1/s0);  dp = -gain J^{-1} e_T
        T_base_flange <- T_base_flange @ Trans(dp)  (nominal IK)

    until ``|u - u0|, |v - v0| <= threshold_px`` and ``|s - s0| <=
    threshold_size_px`` (then ``repeat_captures - 1`` more still captures) or
    the iteration limit. The robot is still at every capture (settling time
    after each move) unless the capture-while-moving fault says otherwise.
    The faults (:mod:`pipeline.sim.faults`) act through the adapter's hooks.

Modules: the world (:mod:`pipeline.sim.cell`), the planned poses
(:mod:`pipeline.sim.poses`), clock, motion and capture
(:mod:`pipeline.sim.session`), faults and truth (:mod:`pipeline.sim.faults`,
:mod:`pipeline.sim.truth`); this module runs the session.

The virtual pin (truth)
    Where a perfect touch-up puts the centre of an untilted target: the circle
    centre whose exactly projected contour (distortion included) fits an
    ellipse with centre ``(u0, v0)`` and long axis ``s0``
    (:func:`pipeline.sim.cell.virtual_pin_camera`); ``p_vt_flange = T_flange_camera p_vt_camera``.
    Near ``fx D / s0`` on the ray of the designated pixel, but about 10 um nearer
    the camera: barrel distortion shrinks the disc's image even on the axis.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.io.mcap_write import Recorder
from pipeline.kinematics.se3 import F64
from pipeline.live.loop import (
    CaptureInfo,
    Detector,
    LoopConfig,
    TouchupResult,
    estimate_jacobian,
    probe_shifts,
    touch_up,
)
from pipeline.live.protocols import Frame
from pipeline.sim import faults
from pipeline.sim.cell import Target
from pipeline.sim.cell_adapter import SimCamera, SimCell
from pipeline.sim.scenario import Scenario
from pipeline.sim.session import CaptureOptions, ImageSource, Session
from pipeline.sim.truth import index_images, truth_of

#: share of the large move after which the capture-while-moving fault's capture starts
#: (at most; :meth:`pipeline.sim.session.Session.large_move` picks a blurring one)
MOVING_CAPTURE_AT = 0.94
#: builds a session's alternative image source (:attr:`pipeline.sim.session.Session.image_source`)
SourceFactory = Callable[[Session], ImageSource]


#: ``progress(done, total)``: touch-up attempts simulated so far, out of the plan's
Progress = Callable[[int, int], None]


def simulate(
    sc: Scenario,
    seed: int,
    out: Path,
    progress: Progress | None = None,
    image_source: SourceFactory | None = None,
) -> dict[str, Any]:
    """Run the session of scenario ``sc`` with ``seed``; write ``out`` (MCAP) and return the truth.

    The MCAP file is written streaming; the truth dictionary has the layout
    of the conformance sample's truth file (see module doc of
    :mod:`pipeline.sim`). ``progress(done, total)`` is called after each touch-up
    attempt (it does not change a byte of the output). ``image_source`` builds, from
    the session, what forms each capture instead of the simulator's renderer (e.g.
    :func:`pipeline.sim.render_pbr.pbr_source`); its ``truth()``, if it has one,
    goes into the truth as ``image_source``.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    with tmp.open("wb") as f:
        rec = Recorder(f, chunk_size=sc.timing.chunk_size)
        cell = SimCell.from_scenario(sc, seed, rec)
        if image_source is not None:
            cell.sess.image_source = image_source(cell.sess)
        truth = _run(cell, progress)
        rec.finish()
    src_truth = getattr(cell.sess.image_source, "truth", None)
    if src_truth is not None:
        truth["image_source"] = src_truth()
    os.replace(tmp, out)
    if sc.faults.truncate:
        truth["truncated"] = faults.truncate_file(
            out, truth, cell.sess.rng_fault, cell.sess.safe_bytes
        )
    return truth


class _Captures:
    """The simulator's :data:`~pipeline.live.loop.OnCapture`: completes each image's truth
    record (kind, touch-up, the controller's detection) and notes its position."""

    def __init__(self, sess: Session) -> None:
        self.sess = sess
        self.positions: list[tuple[str, int]] = []
        self.moving_fault: dict[str, Any] | None = None

    def __call__(self, frame: Frame, info: CaptureInfo) -> None:
        pos = len(self.sess.images) - 1
        rec = self.sess.images[pos]
        assert rec["stamp_ns"] == frame.stamp_ns
        rec["kind"] = info.kind
        rec["touchup"] = info.touchup
        det = info.detection
        rec["sim_detection"] = None if det is None else [float(x) for x in det]
        self.positions.append((info.kind, pos))
        if self.moving_fault is not None:
            # the capture while moving: note it, let the interrupted move finish and settle
            self.moving_fault.update(faults.moving_capture_record(self.sess, pos))
            self.moving_fault = None
            assert self.sess.robot is not None
            self.sess.robot.advance(1.0)


def _run(simcell: SimCell, progress: Progress | None = None) -> dict[str, Any]:
    """Run every attempt of the plan (faulted extras included); return the truth.

    Per attempt: the faults that act before the move (:func:`_faults_before_move`),
    the large move to the planned pose (:func:`_move_to_plan_pose`), a lost target's
    occluder, the image Jacobian probe on a target's first touch-up
    (:func:`_probe_jacobian`), the closed loop (:func:`pipeline.live.loop.touch_up`)
    and the touch-up's truth record (:func:`_record_touchup`).
    """
    sess = simcell.sess
    sc = sess.sc
    rec = sess.rec
    rob = sess.robot
    assert rob is not None
    robot, camera = simcell.robot, simcell.camera
    plan = simcell.plan
    labels = simcell.labels
    faults_at = faults.fault_plan(sess, plan)
    safe_bytes = 0
    if sc.faults.truncate:
        # one more touch-up (a repeat of the first pose) during which the recorder dies
        plan = plan + [plan[0]]
    attempts = faults.attempts(len(plan), faults_at)
    tail_index = len(attempts) - 1 if sc.faults.truncate else -1

    targets = {t.id: t for t in sess.cell.targets}
    jac: dict[int, F64] = {}
    base_cfg = simcell.loop_config()
    detect = simcell.detector()

    for ti, (pi, faulted) in enumerate(attempts):
        tid, q_plan = plan[pi]
        if faulted:  # an extra attempt, rolled off the plan pose (docstring of faults.attempts)
            q_plan = sess.nominal_roll(q_plan, faults.FAULT_ROLL_RAD)
        tg = targets[tid]
        img_start = len(sess.images)
        camera.target = tg
        camera.options = CaptureOptions()
        on_capture = _Captures(sess)
        moving: dict[str, Any] = {}
        # the faults of this attempt: plan index -> fault, on the extra attempt only
        here = {nm: faulted and i == pi for nm, i in faults_at.items()}
        if faults_at["knocked_target"] == pi and (ti == 0 or attempts[ti - 1][0] != pi):
            later = [i for i in range(ti, len(attempts)) if plan[attempts[i][0]][0] == tid]
            faults.knock(sess, tg, ti, labels[tid], later)
        q_plan, cfg, fault_here = _faults_before_move(sess, camera, here, q_plan, base_cfg)

        if ti == tail_index:
            safe_bytes = rec.cut_chunk()
        _move_to_plan_pose(simcell, q_plan, tg, ti, pi, faulted, here, on_capture, moving)

        # ---- lost target: an occluder hides it from the first capture on
        if here["lost_target"]:
            occ, frec = faults.occluder(sess)
            camera.options = dataclasses.replace(camera.options, occluders=(occ,))
            fault_here.append(frec)

        if tid not in jac and not camera.options.occluders:
            _probe_jacobian(simcell, detect, on_capture, cfg, ti, tid, jac)

        # ---- the closed loop
        res = touch_up(robot, camera, detect, on_capture, simcell.goal, cfg, jac.get(tid), ti)
        camera.options = CaptureOptions()
        if here["capture_while_moving"] and moving:
            fault_here.append(moving)
        _record_touchup(sess, ti, tg, labels[tid], cfg, res, on_capture, img_start, fault_here)
        if progress is not None:
            progress(ti + 1, len(attempts))
        # (the knocked target's image indices are filled in below, once all are written)

    rob.advance(1.0)
    rec.flush(None)
    sess.safe_bytes = safe_bytes
    index_images(sess)
    return truth_of(sess, plan, labels, simcell.known, simcell.metadata)


def _faults_before_move(
    sess: Session, camera: SimCamera, here: dict[str, bool], q_plan: F64, cfg: LoopConfig
) -> tuple[F64, LoopConfig, list[dict[str, Any]]]:
    """The faults of an attempt that act before its large move: an unconverged start (off
    the plan pose, a lower gain), a second blob beside the target, a joint-state gap.

    Returns the start pose, the loop settings and the attempt's fault records so far.
    """
    fault_here: list[dict[str, Any]] = []
    if here["unconverged"]:
        q_plan, frec = faults.unconverged_start(sess, q_plan)
        cfg = dataclasses.replace(cfg, gain=faults.UNCONVERGED_GAIN)
        fault_here.append(frec)
    if here["second_blob"]:
        disc, frec = faults.second_blob(sess)
        camera.options = dataclasses.replace(camera.options, extra_discs=(disc,))
        fault_here.append(frec)
    if here["joint_state_gap"]:
        faults.open_gap(sess)
    return q_plan, cfg, fault_here


def _move_to_plan_pose(
    simcell: SimCell,
    q_plan: F64,
    tg: Target,
    ti: int,
    pi: int,
    faulted: bool,
    here: dict[str, bool],
    on_capture: _Captures,
    moving: dict[str, Any],
) -> None:
    """The large move of attempt ``ti`` to plan pose ``pi`` (stopped short by the
    capture-while-moving fault, noted in ``moving``), then the touch-up's own noise streams
    (:meth:`pipeline.sim.session.Session.reseed`) and the joint-state gap's record."""
    sess, robot = simcell.sess, simcell.robot
    rob = sess.robot
    assert rob is not None
    n_dropped = len(rob.dropped)
    if here["capture_while_moving"]:
        robot.stop_next_move = (MOVING_CAPTURE_AT, tg)
        on_capture.moving_fault = moving
    robot.move_joints(q_plan, 1.0)
    if not here["capture_while_moving"]:
        # at the planned pose: from here on this touch-up's noise is its own (clock
        # phase and random streams depend on the plan pose only), so a touch-up is
        # the same whatever faulted attempts came before it
        rob.align_to_tick()
    sess.reseed(pi, faulted)
    if here["joint_state_gap"]:
        sess.faults.append(faults.gap_record(sess, ti, n_dropped))


def _probe_jacobian(
    simcell: SimCell,
    detect: Detector,
    on_capture: _Captures,
    cfg: LoopConfig,
    ti: int,
    tid: int,
    jac: dict[int, F64],
) -> None:
    """Probe target ``tid``'s image Jacobian on its first touch-up ``ti`` (into ``jac``,
    unless the probe failed) and note the probe in the session's truth."""
    J = estimate_jacobian(simcell.robot, simcell.camera, detect, on_capture, simcell.goal, cfg, ti)
    if J is not None:
        jac[tid] = J
    p_imgs = [p for _, p in on_capture.positions]
    simcell.sess.probes.append(
        {
            "target": tid,
            "touchup": ti,
            "image_indices": p_imgs,
            "base_image_index": p_imgs[0],
            "shifts_m": [d.tolist() for d in probe_shifts(cfg.probe_shift_m)],
            "shift_m": cfg.probe_shift_m,
            "jacobian": jac[tid].tolist() if tid in jac else None,
        }
    )


def _record_touchup(
    sess: Session,
    ti: int,
    tg: Target,
    label: int,
    cfg: LoopConfig,
    res: TouchupResult,
    on_capture: _Captures,
    img_start: int,
    fault_here: list[dict[str, Any]],
) -> None:
    """Append touch-up ``ti``'s truth record (its images from ``img_start`` on) and the
    records of the faults of its attempt."""
    q = res.joints.positions
    conv_images: list[int] = []
    if res.converged:
        loops = [p for kind, p in on_capture.positions if kind == "loop"]
        conv_images = loops[-1:] + [p for kind, p in on_capture.positions if kind == "extra"]
    pin = sess.true_pin(q)
    tu_imgs = list(range(img_start, len(sess.images)))
    sess.touchups.append(
        {
            "index": ti,
            "target": tg.id,
            "label": label,
            "converged": res.converged,
            "lost": res.lost,
            "iterations": res.iterations,
            "gain": cfg.gain,
            "q": [float(x) for x in q],
            "image_indices": tu_imgs,
            "converged_image_indices": conv_images,
            "final_error_px": None
            if res.final_error_px is None
            else [float(x) for x in res.final_error_px],
            "target_centre": tg.centre.tolist(),
            "pin_miss_mm": ((pin - tg.centre) * 1000.0).tolist(),
            "in_file": True,
        }
    )
    for fh in fault_here:
        fh.setdefault("touchup", ti)
        if fh["type"] == "unconverged":
            fh["converged"] = res.converged
        if fh["type"] == "target_lost":
            fh["lost"] = res.lost
            fh["_images"] = tu_imgs[:1]
        fh.setdefault("_images", tu_imgs)
        sess.faults.append(fh)


def write_recording(
    sc: Scenario,
    seed: int,
    out: Path,
    progress: Progress | None = None,
    image_source: SourceFactory | None = None,
) -> dict[str, Any]:
    """Simulate and write ``out`` plus ``out.truth.json``; return the truth.

    ``progress(done, total)``: touch-up attempts simulated; ``image_source``: what
    forms the captures (:func:`simulate`)."""
    truth = simulate(sc, seed, out, progress, image_source)
    tpath = Path(str(out) + ".truth.json")
    tmp = tpath.with_name(tpath.name + ".part")
    tmp.write_text(json.dumps(truth, indent=1))
    os.replace(tmp, tpath)
    return truth
