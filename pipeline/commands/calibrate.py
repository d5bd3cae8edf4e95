"""``vtcal calibrate``: plan -> measure -> run for a cell, with the adapters of ``vtcal measure``.

Writes into ``--out``: ``plan.parquet`` (unless ``--plan`` is given),
``recording.mcap`` (resumable, as ``vtcal measure``'s), the run folder
``run/`` and ``measure.json`` (how many touch-ups converged, how long
measuring took). Run again after an interruption, it resumes the measurement
(a complete recording is not measured again) and the run skips what is done.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from pipeline.commands.measure import measure_options, run_measure
from pipeline.errors import BadInput
from pipeline.measure.summary import summarize, summary_line


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
) -> None:
    """Plan, measure and calibrate a cell in one command."""
    from pipeline.commands import plan as plan_cmd
    from pipeline.commands import run as run_cmd
    from pipeline.measure.record import read_progress

    out.mkdir(parents=True, exist_ok=True)
    if plan_path is None:
        if targets_path is None or poses is None or urdf_path is None:
            raise BadInput("vtcal calibrate: give --plan, or --urdf, --targets and --poses to plan")
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
    rec = out / "recording.mcap"
    done = read_progress(rec)
    if done is not None and done.finished:  # measured before: go on with the run
        s = summarize(done.touchups, done.n_plan, done.sessions, rec)
    else:
        s = run_measure(
            plan_path, robot, camera, rec, urdf_path, overrides, speed, max_iterations, gain,
            limit_margin_deg, quiet,
        )  # fmt: skip
    line = summary_line(s)
    click.echo(f"{rec}: {line}")
    run_dir = out / "run"
    run_dir.mkdir(exist_ok=True)
    (out / "measure.json").write_text(json.dumps({**s, "summary": line}, indent=1) + "\n")
    ctx.invoke(run_cmd.command, recording=rec, out=run_dir, quiet=quiet)
    click.echo(f"  {line}")
