"""``vtcal measure``: run a plan on a cell through its adapters and record it (docs/measure.md)."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from pipeline.commands._common import set_option
from pipeline.errors import BadInput, CellFault
from pipeline.live.summary import as_metadata, summarize, summary_line

if TYPE_CHECKING:
    from pipeline.live.cell_link import CellLink
    from pipeline.live.detector import LiveDetector
    from pipeline.live.loop import LoopConfig
    from pipeline.live.plan_file import Plan
    from pipeline.live.session import SessionOptions

#: cell time the arm stays still after each capture (s): more than ingest's still window
#: (+-0.06 s about the stamp) plus half an exposure
HOLD_S = 0.1
#: the servo gain ``vtcal measure`` takes by default: the full linear step (the Jacobian is
#: probed and then updated from the loop's own steps, so one step from the planned pose
#: lands within the thresholds on the standard cells: 2 loop captures where 0.9 took 3)
MEASURE_GAIN = 1.0

ADAPTER_HELP = "tcp://HOST:PORT, sim:SCENARIO.toml:SEED"
CAMERA_HELP = "opencv:INDEX|URL, folder:PATH, or omit: the robot's link serves CAPTURE"


def measure_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """The options ``vtcal measure`` and ``vtcal calibrate`` share."""
    opts: list[Callable[[Callable[..., Any]], Callable[..., Any]]] = [
        click.option("--robot", required=True, metavar="ADAPTER", help=f"Robot: {ADAPTER_HELP}."),
        click.option("--camera", default=None, metavar="ADAPTER", help=f"Camera: {CAMERA_HELP}."),
        click.option(
            "--urdf",
            "urdf_path",
            type=click.Path(dir_okay=False, path_type=Path),
            default=None,
            help="Nominal URDF file, or built-in lrmate/ur5e/iiwa7 (default: the one the cell "
            "serves, URDF?).",
        ),
        set_option,
        click.option("--speed", type=click.FloatRange(0.01, 1.0), default=0.5, show_default=True,
                     help="Speed of the large moves (0-1 of the adapter's maximum)."),
        click.option("--max-iterations", type=click.IntRange(1, 100), default=12, show_default=True,
                     help="Loop captures per touch-up before it gives up."),
        click.option("--gain", type=click.FloatRange(0.05, 1.0), default=MEASURE_GAIN,
                     show_default=True,
                     help="Fraction of the linear correction per servo step."),
        click.option("--order", type=click.Choice(["plan", "travel"]), default="plan",
                     show_default=True,
                     help="Visit the poses in the plan's order, or in the order of shortest "
                     "joint travel (the paths between poses change: dry-run it first)."),
        click.option("--limit-margin-deg", type=click.FloatRange(0.0, 30.0), default=0.0,
                     show_default=True, help="Refuse poses closer than this to a joint limit."),
        click.option("--quiet", "-q", is_flag=True, help="No live progress."),
    ]  # fmt: skip
    for o in reversed(opts):
        fn = o(fn)
    return fn


@contextlib.contextmanager
def _progress(enabled: bool, n: int) -> Iterator[Callable[[Any], None]]:
    """Live progress: a bar over the touch-ups, the current ``e_T``, one line per outcome."""
    if not enabled:
        yield lambda ev: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with Progress(
        TextColumn("[bold]touch-up"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.description}"),
    ) as bars:
        task = bars.add_task("", total=n)

        def show(ev: Any) -> None:
            e = ev.error_px
            err = "" if e is None else f"e_T ({e[0]:+.2f}, {e[1]:+.2f}, {e[2]:+.2f}) px"
            if ev.kind == "start":
                bars.update(task, completed=ev.index, description=f"target {ev.target_id}")
            elif ev.kind == "capture":
                bars.update(task, description=f"target {ev.target_id} {err}")
            else:
                bars.update(task, completed=ev.index + 1)
                bars.console.print(
                    f"touch-up {ev.index + 1}/{ev.n} target {ev.target_id}: {ev.reason}"
                    + (f", {err}" if err else "")
                )

        yield show


def run_measure(
    plan_path: Path,
    robot: str,
    camera: str | None,
    out: Path,
    urdf_path: Path | None,
    overrides: dict[str, str],
    speed: float,
    max_iterations: int,
    gain: float,
    limit_margin_deg: float,
    quiet: bool,
    dry_run: bool = False,
    order: str = "plan",
) -> dict[str, Any]:
    """Measure ``plan_path`` on the cell into ``out``; return the measurement summary.

    ``order`` is ``plan`` (the file's order) or ``travel``
    (:func:`pipeline.live.plan_file.in_travel_order`).

    Raises
    ------
    BadInput
        Plan, URDF or adapter strings not usable; ``out`` not resumable.
    PlanRefused
        A planned pose outside the joint limits (nothing moved).
    CellFault
        A fault at the cell; the recording so far is kept and resumable.
    """
    import numpy as np

    from pipeline.live.plan_file import check_limits, in_travel_order, read_plan
    from pipeline.live.protocols import MeasureFault
    from pipeline.live.session import SessionOptions
    from pipeline.live.session import dry_run as visit
    from pipeline.sim.adapters import connect

    def fault(exc: MeasureFault, what: str) -> CellFault:
        return CellFault(f"{what}: {exc.kind}: {exc}")

    try:
        link = connect(robot, camera)
    except MeasureFault as exc:
        raise fault(exc, robot) from None
    try:
        urdf = _urdf_of(urdf_path, link.urdf, robot)
        plan = read_plan(plan_path, link.robot.joint_names)
        check_limits(plan, urdf, float(np.radians(limit_margin_deg)))
        # the cell's known distances restated by target ids (its first-touch labels follow
        # the file's order); --set ones are by ids already
        labels_from = plan.target_ids
        if order == "travel":
            plan = in_travel_order(plan)
        meta = {**with_target_order(dict(link.metadata), plan.target_ids, labels_from), **overrides}
        # hold still HOLD_S after each capture: ingest judges stillness from the joint
        # states within +-60 ms of the stamp, so the next move must not start inside it
        cfg = loop_config(gain, max_iterations)
        opts = SessionOptions(speed=speed)
        if not quiet:
            click.echo(f"vtcal measure: {len(plan)} poses from {plan_path}; {link.description}")
        if dry_run:
            wall0 = time.perf_counter()
            with _progress(not quiet, len(plan)) as show:
                visit(link, plan, cfg, opts, show)
            return {"dry_run": True, "n_plan": len(plan), "wall_s": time.perf_counter() - wall0}
        return _measure_into(out, link, plan, urdf, meta, cfg, opts, quiet)
    except MeasureFault as exc:
        raise fault(exc, robot) from None
    finally:
        link.close()


def loop_config(gain: float, max_iterations: int) -> LoopConfig:
    """The loop ``vtcal measure`` runs: the Jacobian updated from the loop's own steps
    (Broyden), the arm held still ``HOLD_S`` after each capture, the loop's other defaults
    (3 captures at convergence)."""
    from pipeline.live.loop import LoopConfig

    return LoopConfig(
        gain=gain, max_iterations=max_iterations, update_jacobian=True, compute_s=HOLD_S
    )


def with_target_order(
    meta: dict[str, str], target_ids: list[int], labels_from: list[int] | None = None
) -> dict[str, str]:
    """The metadata with ``target_order``: the plan's target ids in first-visit order.

    The recorder knows the order, so the cell can name its targets (and its bar, in
    ``known_distances``) by the ids of its targets file. Known distances the cell
    states in first-touch labels (0, 1, ... in the order of ``labels_from``, default
    ``target_ids``: the plan file's order, in which the simulated cell's own plan
    visits them; right when the plan measured is the cell's own) are restated by
    those names, whatever order the run then visits them in (``target_ids``).
    """
    if "target_order" in meta:
        return meta
    order = [str(t) for t in dict.fromkeys(target_ids)]
    named = [str(t) for t in dict.fromkeys(target_ids if labels_from is None else labels_from)]
    out = {**meta, "target_order": ",".join(order)}
    text = meta.get("known_distances")
    if text:
        from pipeline.io.known_distances import parse_distances

        items = parse_distances(text)
        if all(isinstance(x, int) and 0 <= x < len(named) for a, b, _ in items for x in (a, b)):
            out["known_distances"] = ";".join(
                f"{named[int(a)]}:{named[int(b)]}={m!r}" for a, b, m in items
            )
        else:  # not first-touch labels: leave the metadata as the cell gave it
            del out["target_order"]
    return out


def _urdf_of(urdf_path: Path | None, served: str | None, robot: str) -> str:
    """The nominal URDF: the file given, else the one the cell serves (BadInput if neither)."""
    if urdf_path is not None:  # a file, or a built-in robot's name (as vtcal plan takes)
        from pipeline.robots import load_urdf

        return load_urdf(str(urdf_path))
    if served is not None:
        return served
    raise BadInput(f"{robot}: the cell serves no URDF (URDF?); give --urdf")


def _measure_into(
    out: Path,
    link: CellLink,
    plan: Plan,
    urdf: str,
    meta: dict[str, str],
    cfg: LoopConfig,
    opts: SessionOptions,
    quiet: bool,
) -> dict[str, Any]:
    """Touch up every pose of ``plan`` into the recording ``out`` (resumed if it holds some).

    The designated blob comes from ``meta`` (the image size from one capture when it
    does not say); a fault leaves the recording so far, resumable (CellFault).
    """
    from pipeline.live.protocols import MeasureFault
    from pipeline.live.record import open_recording
    from pipeline.live.session import goal_from_metadata, run_session

    size = None
    if "designated_u" not in meta or "designated_v" not in meta:
        img = link.camera.capture().image  # before any move: the image size only
        size = (int(img.shape[1]), int(img.shape[0]))
    goal = goal_from_metadata(meta, size)
    meta.setdefault("designated_u", f"{goal.u0:g}")
    meta.setdefault("designated_v", f"{goal.v0:g}")
    detect = _detector(meta, goal.polarity, goal.s0, quiet)
    link.drain_joints()  # samples from before the recording starts
    t0 = link.robot.read_joints().stamp_ns
    rec = open_recording(out, urdf, meta, plan.sha256, len(plan), t0)
    if rec.progress.sessions > 1:
        detect.resume(rec.progress.state)  # a response estimated before stays
        behind = rec.progress.safe_log_ns - link.robot.read_joints().stamp_ns
        if behind >= 0:  # a cell whose clock restarted (a simulated one): let it pass
            link.robot.wait(behind / 1e9 + 1.0)
        if not quiet:
            click.echo(f"vtcal measure: resuming {out} at touch-up {rec.progress.done + 1}")
    try:
        with _progress(not quiet, len(plan)) as show:
            run_session(link, plan, rec, goal, cfg, detect, opts, show)
    except MeasureFault as exc:
        rec.abandon()
        raise CellFault(
            f"{out}: {exc.kind}: {exc}; the recording so far is kept "
            f"({rec.progress.done} of {len(plan)} touch-ups), run the same command to resume"
        ) from None
    except BaseException:
        rec.abandon()
        raise
    done = summarize(rec.progress.touchups, len(plan), rec.progress.sessions, out)
    done["camera_response"] = detect.response
    done["camera_response_source"] = detect.source
    rec.finish(as_metadata(done))
    return done


def _detector(meta: dict[str, str], polarity: str, s0: float, quiet: bool) -> LiveDetector:
    """The loop's detector, linearising with the ``camera_response`` of ``meta`` (the cell's
    ``META?`` merged with ``--set``); without one it estimates the response from its first
    clean captures and says so on stderr.

    Raises
    ------
    BadInput
        A ``camera_response`` that is not a response curve.
    """
    from pipeline.live.detector import vtcal_detector

    text = meta.get("camera_response", "auto")
    try:
        detect = vtcal_detector(
            polarity,
            size_px=s0,
            response=text,
            say=lambda m: click.echo(f"vtcal measure: {m}", err=True),
        )
    except ValueError as exc:
        raise BadInput(f"touchup metadata: camera_response={text!r}: {exc}") from None
    if not quiet:
        click.echo(
            f"vtcal measure: camera response {detect.response} (declared: camera_response)"
            if detect.source == "declared"
            else "vtcal measure: camera response not declared: estimating it from the first "
            "clean captures"
        )
    return detect


@click.command(
    "measure",
    epilog="""\b
Examples:
  vtcal measure --plan plan.parquet --robot tcp://192.168.0.10:30010 --camera opencv:0 --out rec.mcap
  vtcal measure --plan plan.parquet --robot sim:datasets/scenarios/standard.toml:1 --out rec.mcap
  vtcal measure --plan plan.parquet --robot tcp://127.0.0.1:5000 --out rec.mcap --dry-run
""",
)
@click.option("--plan", "plan_path", required=True, type=click.Path(path_type=Path),
              help="Measuring poses (vtcal plan's Parquet).")  # fmt: skip
@click.option("--out", "-o", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Recording to write (MCAP); a partial one is resumed.")  # fmt: skip
@click.option(
    "--dry-run", is_flag=True, help="Only visit the poses, slowly; no touch-up, no recording."
)
@measure_options
def command(
    plan_path: Path,
    out: Path,
    dry_run: bool,
    robot: str,
    camera: str | None,
    urdf_path: Path | None,
    overrides: dict[str, str],
    speed: float,
    max_iterations: int,
    gain: float,
    limit_margin_deg: float,
    quiet: bool,
    order: str,
) -> None:
    """Run a plan on a cell: move, touch up, record (crash-safe, resumable)."""
    s = run_measure(
        plan_path, robot, camera, out, urdf_path, overrides, speed, max_iterations, gain,
        limit_margin_deg, quiet, dry_run, order,
    )  # fmt: skip
    if s.get("dry_run"):
        click.echo(f"dry run: visited {s['n_plan']} poses in {s['wall_s']:.1f} s; nothing recorded")
        return
    click.echo(f"{out}: {summary_line(s)}")
