"""``vtcal cell-server``: the simulated cell behind the cell protocol (docs/measure.md)."""

from __future__ import annotations

from pathlib import Path

import click


@click.command(
    "cell-server",
    epilog="""\b
Examples:
  vtcal cell-server --scenario datasets/scenarios/standard.toml --seed 1 --port 5000 \\
      --plan-out plan.parquet &
  vtcal cell-server --scenario datasets/scenarios/ur.toml --port 0     # a free port, printed
""",
)
@click.option("--scenario", "scenario_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Scenario TOML of the simulated cell.")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", type=click.IntRange(0, 65535), default=5000, show_default=True,
              help="TCP port (0: a free one, printed).")  # fmt: skip
@click.option("--plan-out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the scenario's measuring poses as a plan for vtcal measure.")  # fmt: skip
@click.option("--withhold", multiple=True, metavar="KEY",
              help="Leave this touchup metadata key out of META? (a cell that does not know "
                   "it, e.g. camera_response); repeatable.")  # fmt: skip
def command(
    scenario_path: Path,
    seed: int,
    host: str,
    port: int,
    plan_out: Path | None,
    withhold: tuple[str, ...],
) -> None:
    """Serve the simulated cell of SCENARIO and SEED on HOST:PORT until interrupted."""
    from pipeline.live.tcp_server import Cell, CellServer
    from pipeline.sim.link import sim_cell, write_plan

    cell, tap = sim_cell(f"sim:{scenario_path}:{seed}")
    if plan_out is not None:
        write_plan(cell, str(plan_out))
    meta = {k: v for k, v in cell.served_metadata.items() if k not in withhold}
    server = CellServer(
        Cell(cell.robot, cell.camera, tap.since, cell.nominal_urdf, meta), host, port
    )
    click.echo(
        f"vtcal cell-server: tcp://{host}:{server.port} ({scenario_path}, seed {seed})", err=True
    )
    try:
        server.serve_forever()
    finally:
        server.server_close()
