"""One measuring session: the plan's poses in order, each touched up and recorded.

The client of the shared loop (:mod:`pipeline.live.loop`) that ``vtcal
measure`` runs: for each pose from the first unfinished one on, a large move
(:meth:`Robot.move_joints`), the image Jacobian at the first touch-up of each
target (:func:`~pipeline.live.loop.estimate_jacobian`, paper sec. 2.1; then
carried to the target's next touch-ups, updated by the loop's own steps), the touch-up
(:func:`~pipeline.live.loop.touch_up`), and every frame and joint sample
into the live recording (:mod:`pipeline.live.record`). What the session
learns (the Jacobian) is saved with each finished touch-up, so a resumed run
goes on with it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.live.cell_link import CellLink
from pipeline.live.loop import (
    CaptureInfo,
    Detector,
    Goal,
    LoopConfig,
    estimate_jacobian,
    touch_up,
    wait_still,
)
from pipeline.live.plan_file import Plan
from pipeline.live.protocols import Frame, MeasureFault
from pipeline.live.record import LiveRecording
from pipeline.live.timing import seconds, timed

NS = 1_000_000_000


@dataclass(frozen=True)
class SessionOptions:
    """How the plan is run.

    Attributes
    ----------
    speed : joint speed of the large moves (0-1 of the adapter's maximum)
    dry_run_speed : speed of a dry run's moves
    max_lost_in_a_row : that many touch-ups in a row without the target stop the
        run with a ``target_not_found`` fault (one alone is recorded and skipped)
    """

    speed: float = 0.5
    dry_run_speed: float = 0.1
    max_lost_in_a_row: int = 3


@dataclass(frozen=True)
class Event:
    """What the progress display shows: ``kind`` is ``start``, ``capture`` or ``done``."""

    kind: str
    index: int
    n: int
    target_id: int
    error_px: tuple[float, float, float] | None = None
    reason: str = ""


def _error_px(goal: Goal, info: CaptureInfo) -> tuple[float, float, float] | None:
    return None if info.detection is None else goal.error_px(info.detection)


def run_session(
    link: CellLink,
    plan: Plan,
    rec: LiveRecording,
    goal: Goal,
    cfg: LoopConfig,
    detect: Detector,
    opts: SessionOptions,
    report: Callable[[Event], None],
) -> list[dict[str, Any]]:
    """Measure the plan's poses from ``rec.progress.done`` on; return the session's summaries.

    Each summary (also saved in the recording's progress file) holds the
    touch-up's place in the run (``index``) and its row of the plan file
    (``plan_row``: another one after ``--order travel``), target, outcome (``converged``, ``reason``), ``iterations``,
    ``captures`` (probes included), ``final_error_px``, ``cell_s`` (cell clock
    from the start of the large move to the last capture), its split
    ``travel_s``, ``settle_s``, ``servo_s``, ``capture_s``
    (:mod:`pipeline.live.timing`; they sum to ``cell_s``) and ``wall_s``.

    Raises
    ------
    MeasureFault
        From the adapters, or ``target_not_found`` after
        ``opts.max_lost_in_a_row`` touch-ups in a row lost their target.
    """
    robot, camera, clock = timed(link.robot, link.camera)
    names = robot.joint_names
    state = rec.progress.state
    jacobians = {int(k): np.array(v, dtype=float) for k, v in state.get("jacobians", {}).items()}
    lost_in_a_row = int(state.get("lost_in_a_row", 0))
    out: list[dict[str, Any]] = []

    probes = [0]  # probe captures of the touch-up in progress

    def joints() -> None:
        samples = link.drain_joints()
        clock.observe(samples)
        rec.joints(names, samples)

    def on_capture(frame: Frame, info: CaptureInfo) -> None:
        probes[0] += info.kind == "probe"
        joints()
        rec.image(frame)
        report(Event("capture", i, len(plan), tid, _error_px(goal, info)))

    for i in range(rec.progress.done, len(plan)):
        tid = plan.target_ids[i]
        report(Event("start", i, len(plan), tid))
        wall0 = time.perf_counter()
        t0 = clock.start()
        robot.move_joints(plan.q[i], opts.speed)
        probes[0] = 0
        J = jacobians.get(tid)
        if J is None:
            J = estimate_jacobian(robot, camera, detect, on_capture, goal, cfg, i)
        n_probe = probes[0]
        res = touch_up(robot, camera, detect, on_capture, goal, cfg, J, i)
        if res.jacobian is not None and res.reason != "no_jacobian":
            jacobians[tid] = res.jacobian
        joints()
        lost_in_a_row = 0 if res.converged or not res.lost else lost_in_a_row + 1
        summary = {
            "index": i,
            "plan_row": plan.row(i),
            "target_id": tid,
            "converged": res.converged,
            "reason": res.reason,
            "iterations": res.iterations,
            "captures": n_probe + len(res.captures),
            "probe_captures": n_probe,
            "final_error_px": None if res.final_error_px is None else list(res.final_error_px),
            "cell_s": (res.joints.stamp_ns - t0) / NS,
            **seconds(clock.split(res.joints.stamp_ns)),
            "wall_s": time.perf_counter() - wall0,
        }
        out.append(summary)
        rec.touchup_done(
            summary,
            {
                "jacobians": {str(k): v.tolist() for k, v in jacobians.items()},
                "lost_in_a_row": lost_in_a_row,
                # what the detector learned (an estimated camera response), kept on resume
                **(learned() if callable(learned := getattr(detect, "learned", None)) else {}),
            },
        )
        report(Event("done", i, len(plan), tid, res.final_error_px, res.reason))
        if lost_in_a_row >= opts.max_lost_in_a_row:
            raise MeasureFault(
                "target_not_found",
                f"touch-ups {i - lost_in_a_row + 2}..{i + 1}: the target was not found "
                f"{lost_in_a_row} times in a row (last: target {tid}, {res.reason})",
            )
    return out


def dry_run(
    link: CellLink,
    plan: Plan,
    cfg: LoopConfig,
    opts: SessionOptions,
    report: Callable[[Event], None],
) -> None:
    """Visit every planned pose at ``opts.dry_run_speed``, waiting for stillness; no touch-up."""
    for i in range(len(plan)):
        report(Event("start", i, len(plan), plan.target_ids[i]))
        link.robot.move_joints(plan.q[i], opts.dry_run_speed)
        wait_still(link.robot, cfg)
        report(Event("done", i, len(plan), plan.target_ids[i], reason="visited"))


def goal_from_metadata(meta: dict[str, str], image_size: tuple[int, int] | None) -> Goal:
    """The loop's :class:`Goal` from the recording's ``touchup`` keys (spec ``recording.md``).

    ``designated_u``/``designated_v`` default to the image centre
    ``((W - 1) / 2, (H - 1) / 2)`` of ``image_size = (W, H)``; the thresholds to
    0.5 px; the polarity to ``dark_on_light``. ``designated_size_px`` has no
    default (it sets the stand-off).

    Raises
    ------
    BadInput
        A missing ``designated_size_px`` or a value that is not a number.
    """
    from pipeline.errors import BadInput

    def num(key: str, default: float | None) -> float:
        if key not in meta:
            if default is None:
                raise BadInput(
                    f"touchup metadata: {key} is needed (the cell does not say it; "
                    f"give --set {key}=VALUE)"
                )
            return default
        try:
            return float(meta[key])
        except ValueError:
            raise BadInput(f"touchup metadata: {key}={meta[key]!r} is not a number") from None

    w, h = image_size if image_size is not None else (None, None)
    cu = None if w is None else (w - 1) / 2.0
    cv = None if h is None else (h - 1) / 2.0
    polarity = meta.get("polarity", "dark_on_light")
    if polarity not in ("dark_on_light", "light_on_dark"):
        raise BadInput(f"touchup metadata: polarity={polarity!r}: dark_on_light or light_on_dark")
    return Goal(
        u0=num("designated_u", cu),
        v0=num("designated_v", cv),
        s0=num("designated_size_px", None),
        threshold_px=num("threshold_px", 0.5),
        threshold_size_px=num("threshold_size_px", 0.5),
        polarity=polarity,
    )
