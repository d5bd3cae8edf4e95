"""``vtcal calibrate``: plan -> measure -> run for a cell, with the adapters of ``vtcal measure``.

Writes into ``--out``: ``plan.parquet`` and what it was planned from,
``plan.request.json`` (unless ``--plan`` is given; a rerun asking for another
plan, or with ``--plan`` another than the finished recording followed, is refused),
``recording.mcap`` (resumable, as ``vtcal measure``'s), the run folder
``run/`` and ``measure.json`` (how many touch-ups converged, how long
measuring took). Run again after an interruption, it resumes the measurement
(a complete recording is not measured again) and the run skips what is done.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import click

from pipeline.commands.measure import measure_options, run_measure
from pipeline.errors import BadInput
from pipeline.live.summary import summarize, summary_line
from pipeline.robots import load_urdf

#: what the plan in ``--out`` was planned from (hashes of the URDF and the targets file,
#: poses, pin, seed): a rerun asking for another plan is refused, not silently served
#: the old plan and recording
PLAN_REQUEST = "plan.request.json"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _same_plan_request(out: Path, request: dict[str, object], poses: int) -> None:
    """Refuse when ``out`` holds a plan made from another request (BadInput naming both)."""
    old_path = out / PLAN_REQUEST
    if not (out / "plan.parquet").exists():
        return
    try:
        old = json.loads(old_path.read_text())
    except (OSError, ValueError):
        old = None
    if old == request:
        return
    what = (
        f"--poses {old.get('poses')}"
        if isinstance(old, dict) and old.get("poses") != poses
        else "other --urdf/--targets/--pin/--plan-seed"
        if isinstance(old, dict)
        else f"an unknown request (no readable {PLAN_REQUEST})"
    )
    raise BadInput(
        f"{out}: holds a plan (and maybe a recording) made with {what}; this run asks "
        f"--poses {poses}: use another --out, or move plan.parquet and recording.mcap away"
    )


def _xyz(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise BadInput(f"--pin {text!r}: expected X,Y,Z in metres") from None
    return x, y, z


@click.command(
    "calibrate",
    epilog="""\b
Examples:
  vtcal calibrate --robot sim:datasets/scenarios/standard.toml:1 --urdf pipeline/robots/lrmate.urdf \\
      --targets datasets/targets/lrmate_cell.csv --poses 24 --pin 0.047,0.002,0.251 --out cal/
  vtcal calibrate --robot sim:datasets/scenarios/standard.toml:1 --plan plan.parquet --out cal/
  vtcal calibrate --robot tcp://10.0.0.2:30010 --camera opencv:0 --urdf lrmate \\
      --targets cell.csv --poses 24 --pin 0.03,0,0.25 --out cal/
""",
)
@click.option(
    "--out",
    "-o",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder for the plan, the recording, measure.json and the run folder run/.",
)
@click.option(
    "--plan",
    "plan_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Use this plan instead of planning (then --targets/--poses are not needed).",
)
@click.option(
    "--targets",
    "targets_path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Targets CSV for vtcal plan (target_id, x, y, z, nx, ny, nz).",
)
@click.option("--poses", type=int, default=None, help="Poses to plan (vtcal plan --poses).")
@click.option("--pin", default="0,0,0.2", show_default=True, help="vtcal plan --pin X,Y,Z.")
@click.option("--plan-seed", type=int, default=0, show_default=True, help="vtcal plan --seed.")
@measure_options
@click.pass_context
def command(
    ctx: click.Context,
    out: Path,
    plan_path: Path | None,
    targets_path: Path | None,
    poses: int | None,
    pin: str,
    plan_seed: int,
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
    """Plan, measure and calibrate a cell in one command."""
    from pipeline.commands import plan as plan_cmd
    from pipeline.commands import run as run_cmd
    from pipeline.live.record import read_progress

    if plan_path is None:
        if targets_path is None or poses is None or urdf_path is None:
            raise BadInput("vtcal calibrate: give --plan, or --urdf, --targets and --poses to plan")
        if not targets_path.is_file():
            raise BadInput(f"{targets_path}: targets file not found")
        request = {
            "urdf": _sha256(load_urdf(str(urdf_path)).encode()),
            "targets": _sha256(targets_path.read_bytes()),
            "poses": poses,
            "pin": list(_xyz(pin)),
            "plan_seed": plan_seed,
        }
        _same_plan_request(out, request, poses)
        out.mkdir(parents=True, exist_ok=True)
        plan_path = out / "plan.parquet"
        if not plan_path.exists():
            ctx.invoke(
                plan_cmd.command,
                urdf=str(urdf_path),
                targets_path=targets_path,
                poses=poses,
                out=plan_path,
                pin=_xyz(pin),
                seed=plan_seed,
                quiet=quiet,
            )
            (out / PLAN_REQUEST).write_text(json.dumps(request, indent=1) + "\n")
    out.mkdir(parents=True, exist_ok=True)
    rec = out / "recording.mcap"
    done = read_progress(rec)
    if done is not None and done.finished and plan_path.is_file():
        plan_sha = _sha256(plan_path.read_bytes())
        if done.plan_sha256 != plan_sha:  # a finished recording of another plan: not reused
            raise BadInput(
                f"{rec}: was measured with another plan (sha256 {done.plan_sha256[:12]}...) "
                f"than {plan_path} ({plan_sha[:12]}...): use another --out, or move the "
                "recording away to measure this plan"
            )
    if done is not None and done.finished:  # measured before: go on with the run
        s = summarize(done.touchups, done.n_plan, done.sessions, rec)
    else:
        s = run_measure(
            plan_path, robot, camera, rec, urdf_path, overrides, speed, max_iterations, gain,
            limit_margin_deg, quiet, order=order,
        )  # fmt: skip
    line = summary_line(s)
    click.echo(f"{rec}: {line}")
    run_dir = out / "run"
    run_dir.mkdir(exist_ok=True)
    (out / "measure.json").write_text(json.dumps({**s, "summary": line}, indent=1) + "\n")
    ctx.invoke(run_cmd.command, recording=rec, out=run_dir, quiet=quiet)
    click.echo(f"  {line}")
