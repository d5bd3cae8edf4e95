"""``vtcal predict RUN_DIR --joints TABLE --out FILE``: where the calibrated robot puts its tool.

For each row of joint values, the flange pose and the virtual pin's position
in the base frame under the model the run predicts with (``calibration.json``,
compliance included where the run chose ``elastic``), the pin's predicted
uncertainty and a flag where the joints leave the region the calibration
covered. The maths is :mod:`pipeline.use.calibration`; the columns
``schemas/predictions.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    import numpy as np
    import pandas as pd

    from pipeline.use import Calibration


@click.command(
    "predict",
    epilog="""\b
Examples:
  vtcal predict runs/sample --joints datasets/samples/sample_program.csv --out predicted.csv
  vtcal predict runs/panda --joints poses.parquet --out predicted.parquet --payload-kg 0.5
""",
)
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--joints", "joints_path", required=True,
              type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="CSV or Parquet, one column per URDF joint (rad), one row per joint vector; "
              "an optional payload_kg column.")  # fmt: skip
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="File to write: .parquet, else CSV (schemas/predictions.json).")  # fmt: skip
@click.option("--payload-kg", type=click.FloatRange(min=0), default=None,
              help="Payload at the flange for every row without a payload_kg column (default: "
              "the calibration's own; only an elastic model depends on it).")  # fmt: skip
def command(run_dir: Path, joints_path: Path, out_path: Path, payload_kg: float | None) -> None:
    """Predict flange pose and pin position (base frame) at joint values, with uncertainty.

    Uses the model RUN_DIR's calibration.json records (the one its held-out error
    chose; joint compliance included where it is elastic). Rows whose joints leave
    the ranges the calibration's touch-ups covered are flagged (inside_region).
    """
    from pipeline.use import load
    from pipeline.use.table_io import joint_matrix, payload_column, read_rows, write_rows
    from pipeline.use.tables import predict_rows

    cal = load(run_dir)
    df = read_rows(joints_path)
    q = joint_matrix(df, cal.joint_names, joints_path)
    assert q is not None
    payload = payload_column(df, joints_path, payload_kg)
    out = predict_rows(cal, q, payload)
    write_rows(out_path, out, "predictions", "predict")
    _say(cal, out, payload)
    click.echo(f"wrote {len(out)} predictions to {out_path}")


def _say(cal: Calibration, out: pd.DataFrame, payload: np.ndarray) -> None:
    """The console summary: the model, the uncertainty, the rows outside the region."""
    import numpy as np

    from pipeline.io.numfmt import fmt
    from pipeline.use.tables import region_line

    m = cal.model
    sig = out["sigma_pin_m"].to_numpy(dtype=float) * 1e3
    click.echo(str(cal.record.get("choice") or f"predictions use {m}"))
    if np.isfinite(sig).any():
        click.echo(
            f"predicted pin uncertainty (1 sigma): median {fmt(float(np.nanmedian(sig)))} mm, "
            f"max {fmt(float(np.nanmax(sig)))} mm"
        )
    click.echo(region_line(out))
    if np.isfinite(np.asarray(payload, dtype=float)).any() and not getattr(
        cal, "has_payload", False
    ):
        click.echo(f"payload: model {m} is rigid, the payload changes nothing it predicts")
