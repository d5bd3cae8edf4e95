"""``vtcal simulate``: write a simulated touch-up recording and its ground truth."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import click

from pipeline.errors import BadInput


@click.command(
    "simulate",
    epilog="""\b
Examples:
  vtcal simulate --scenario datasets/scenarios/standard.toml --seed 1 --out rec.mcap
  vtcal simulate --scenario datasets/scenarios/small.toml --seed 3 --out small.mcap --quiet
  vtcal simulate --scenario datasets/scenarios/standard.toml --plan plan.parquet --out rec.mcap
""",
)
@click.option(
    "--scenario",
    "scenario_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Scenario TOML (datasets/scenarios/NAME.toml).",
)
@click.option(
    "--seed", type=int, default=0, show_default=True, help="Random seed (same seed, same bytes)."
)
@click.option(
    "--out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Output REC.mcap; REC.mcap.truth.json is written beside it.",
)
@click.option(
    "--plan",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Measuring poses (Parquet: target_id + one column per joint); overrides the scenario.",
)
@click.option("--quiet", is_flag=True, help="Print nothing on success.")
def command(scenario_path: Path, seed: int, out: Path, plan: Path | None, quiet: bool) -> None:
    """Simulate a touch-up recording (MCAP, ROS 2) with ground truth beside it."""
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import write_recording

    sc = load_scenario(scenario_path)
    if plan is not None:
        if not plan.exists():
            raise BadInput(f"{plan}: plan file not found")
        sc = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, plan=str(plan.resolve())))
    from pipeline.commands._common import progress_bars

    t0 = time.perf_counter()
    with progress_bars(enabled=not quiet) as bar:
        truth = write_recording(
            sc, seed, out, None if bar is None else (lambda d, n: bar("touch-ups", d, n))
        )
    if not quiet:
        c = truth["counts"]
        conv = sum(1 for t in truth["touchups"] if t["converged"])
        click.echo(
            f"{out}: {c['images']} images, {c['joint_states']} joint states, "
            f"{conv}/{c['touchups']} touch-ups converged, {len(truth['faults'])} faults "
            f"({time.perf_counter() - t0:.1f} s); truth: {out}.truth.json"
        )
