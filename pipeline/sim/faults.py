"""The simulator's faults (spec ``recording.md``, "Faults a real recording has").

Which touch-up carries which fault (:func:`fault_plan`), the extra faulted
attempts (:func:`attempts`), what each fault does to the cell before its
touch-up (a knocked target, an offset start with a low gain, a second blob, an
occluder, a joint-state gap, a move interrupted for a capture while moving) and
the truth record it leaves, and the truncated file (:func:`truncate_file`). The
touch-up loop itself knows none of them: they act through the cell adapter
(:mod:`pipeline.sim.cell_adapter`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.kinematics.se3 import F64
from pipeline.sim.cell import Target
from pipeline.sim.session import JOINT_LATENCY_NS, NS, Session


def fault_plan(sess: Session, plan: list[tuple[int, F64]]) -> dict[str, int]:
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


def attempts(n_plan: int, faults_at: dict[str, int]) -> list[tuple[int, bool]]:
    """The touch-ups of a session in order: ``(plan index, faulted)``.

    A fault never takes the place of a planned touch-up: a plan pose that carries a
    fault (other than a knock, which happens between touch-ups) is visited twice,
    first by an extra, faulted touch-up at the pose rolled by
    :data:`FAULT_ROLL_RAD` about the camera axis through the pin (so that it is a
    touch-up of its own, not a continuation of the next), then by the planned one.
    A recording with faults thus holds every touch-up of the same seed's
    fault-free recording (with the same noise, see :meth:`pipeline.sim.session.Session.reseed`) plus
    the faulted ones.
    """
    faulted = {i for nm, i in faults_at.items() if nm != "knocked_target" and i >= 0}
    out: list[tuple[int, bool]] = []
    for i in range(n_plan):
        if i in faulted:
            out.append((i, True))
        out.append((i, False))
    return out


def knock(
    sess: Session,
    tg: Target,
    touchup: int,
    label: int,
    later_touchups: list[int],
) -> None:
    """Knock ``tg`` by 1-2 mm in a random direction now (before touch-up ``touchup``)."""
    rob = sess.robot
    assert rob is not None
    t0 = sess.sc.timing.start_ns
    shift = sess.rng_fault.normal(0.0, 1.0, 3)
    shift *= sess.rng_fault.uniform(0.001, 0.002) / np.linalg.norm(shift)
    tg.centre = tg.centre + shift
    tg.history.append(
        {"from_s": (rob.t - t0) / NS, "from_ns": int(rob.t), "centre": tg.centre.tolist()}
    )
    sess.faults.append(
        {
            "type": "target_knocked",
            "target": tg.id,
            "label": label,
            "time_s": (rob.t - t0) / NS,
            "shift_m": shift.tolist(),
            "first_touchup": touchup,
            "centre_after": tg.centre.tolist(),
            "time_ns": int(rob.t),
            "touchups_after": later_touchups,
        }
    )


#: gain of the unconverged fault's touch-up, and how far off its start is (m)
UNCONVERGED_GAIN = 0.2
UNCONVERGED_OFFSET_M = 0.01


def unconverged_start(sess: Session, q_plan: F64) -> tuple[F64, dict[str, Any]]:
    """The unconverged fault: start 10 mm off sideways (nominal flange shift); the
    touch-up runs with gain :data:`UNCONVERGED_GAIN` and runs out of iterations."""
    offset = sess.rng_fault.normal(0.0, 1.0, 3)
    offset[2] = 0.0
    offset *= UNCONVERGED_OFFSET_M / np.linalg.norm(offset)
    q = sess.nominal_shift(q_plan, offset)
    rec = {"type": "unconverged", "gain": UNCONVERGED_GAIN, "plan_offset_m": UNCONVERGED_OFFSET_M}
    return q, rec


def second_blob(sess: Session) -> tuple[tuple[float, float, float, float], dict[str, Any]]:
    """A 4 mm disc 13-20 mm from the target's centre on its plate: ``(extra disc, record)``."""
    ang = sess.rng_fault.uniform(0, 2 * np.pi)
    rad = sess.rng_fault.uniform(0.013, 0.02)
    off = (float(rad * np.cos(ang)), float(rad * np.sin(ang)))
    disc = (off[0], off[1], 0.004, float(sess.levels[0]))
    return disc, {"type": "second_blob", "diameter_m": 0.004, "offset_in_plate_m": list(off)}


def occluder(
    sess: Session,
) -> tuple[tuple[float, float, float, float, float, float], dict[str, Any]]:
    """An ellipse of table grey over the designated pixel (the target is lost)."""
    cell = sess.cell
    occ = (
        float(cell.u0 + sess.rng_fault.normal(0, 5)),
        float(cell.v0 + sess.rng_fault.normal(0, 5)),
        150.0,
        120.0,
        float(sess.rng_fault.uniform(0, np.pi)),
        float(sess.background),
    )
    rec = {
        "type": "target_lost",
        "cause": "occluded",
        "occluder": {
            "centre_px": [occ[0], occ[1]],
            "semi_axes_px": [occ[2], occ[3]],
            "angle_rad": occ[4],
            "grey": occ[5],
        },
    }
    return occ, rec


def open_gap(sess: Session) -> None:
    """Drop the joint states of 0.5 s starting 0.3 s from now."""
    rob = sess.robot
    assert rob is not None
    g0 = rob.t + int(0.3 * NS)
    rob.gaps.append((g0, g0 + int(0.5 * NS)))


def gap_record(sess: Session, touchup: int, n_dropped_before: int) -> dict[str, Any]:
    """The truth record of the joint-state gap just passed."""
    rob = sess.robot
    assert rob is not None
    dropped = rob.dropped[n_dropped_before:]
    n_pre = rob.emitted_before_gap[len(rob.gaps) - 1]
    return {
        "type": "joint_state_gap",
        "touchup": touchup,
        "duration_s": len(dropped) * rob.dt_ns / NS,
        "missing_stamps_ns": [int(dropped[0]), int(dropped[-1])],
        "missing_count": len(dropped),
        "last_index_before": int(n_pre - 1),
        "first_index_after": int(n_pre),
        "log_time_before_ns": int(dropped[0] - rob.dt_ns + JOINT_LATENCY_NS),
        "log_time_after_ns": int(dropped[-1] + rob.dt_ns + JOINT_LATENCY_NS),
    }


def moving_capture_record(sess: Session, image_pos: int) -> dict[str, Any]:
    """The truth record of the capture taken while moving (image at ``image_pos``)."""
    return {
        "type": "capture_while_moving",
        "phase": "approach",
        "exposure_s": max(sess.sc.camera.exposure_s, 0.04),
        "renders": sess.last_renders,
        "blur_px": [sess.images[image_pos]["blur_px"]],
        "_images": [image_pos],
    }


def truncate_file(
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
