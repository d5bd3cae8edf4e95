"""``vtcal compensate RUN_DIR --targets TABLE --out FILE``: joints that reach targets on the calibrated robot.

Targets are flange poses (``x, y, z, qx, qy, qz, qw``: m and a unit quaternion,
base frame), virtual-pin positions (``x, y, z`` with ``--point pin``), or a
joint program recorded on the nominal model (joint columns only: each row's
target is where the nominal robot puts the flange, or the pin, at those
joints). Joint columns beside a pose are the starting joints (the solution
stays on their branch). The maths is :mod:`pipeline.use.inverse`; the columns
``schemas/compensated.json``.
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
    "compensate",
    epilog="""\b
Examples:
  vtcal compensate runs/sample --targets datasets/samples/sample_program.csv --out corrected.csv
  vtcal compensate runs/cell --targets poses.csv --out joints.csv            # x,y,z,qx,qy,qz,qw
  vtcal compensate runs/cell --targets points.csv --point pin --out joints.parquet
""",
)
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--targets", "targets_path", required=True,
              type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="CSV or Parquet: x,y,z[,qx,qy,qz,qw] (base frame, m) with optional starting "
              "joint columns, or joint columns only (a program on the nominal model); an "
              "optional payload_kg column.")  # fmt: skip
@click.option("--out", "out_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="File to write: .parquet, else CSV (schemas/compensated.json).")  # fmt: skip
@click.option("--point", type=click.Choice(["flange", "pin"]), default=None,
              help="What reaches the target: the flange (pose) or the virtual pin (position). "
              "Default: flange when the table has an orientation or is a joint program, pin "
              "for positions alone.")  # fmt: skip
@click.option("--payload-kg", type=click.FloatRange(min=0), default=None,
              help="Payload at the flange for rows without a payload_kg column (default: the "
              "calibration's own; only an elastic model depends on it).")  # fmt: skip
def command(
    run_dir: Path, targets_path: Path, out_path: Path, point: str | None, payload_kg: float | None
) -> None:
    """Joint values that put the calibrated robot's flange or pin on targets.

    Uses the model RUN_DIR's calibration.json records; prints the largest residual
    (compensate then predict lands on the target to about 1e-12 m where it is
    reachable) and flags rows outside the covered joint ranges or the joint limits.
    """
    import numpy as np

    from pipeline.errors import BadInput
    from pipeline.use import load
    from pipeline.use.table_io import (
        finite_columns,
        joint_matrix,
        payload_column,
        read_rows,
        write_rows,
    )
    from pipeline.use.tables import (
        ORIENTATION,
        POSITION,
        compensate_rows,
        nominal_targets,
        target_poses,
    )

    cal = load(run_dir)
    df = read_rows(targets_path)
    q0 = joint_matrix(df, cal.joint_names, targets_path, required=False)
    has_pos = all(c in df.columns for c in POSITION)
    has_rot = all(c in df.columns for c in ORIENTATION)
    if has_pos:
        point = point or ("flange" if has_rot else "pin")
        if point == "flange" and not has_rot:
            raise BadInput(
                f"{targets_path}: a flange target is a pose: columns qx, qy, qz, qw are missing "
                "(or give --point pin for positions of the virtual pin)"
            )
        cols = [*POSITION, *(ORIENTATION if point == "flange" else ())]
        T = target_poses(df, finite_columns(df, cols, targets_path), point == "flange")
        if q0 is None:
            q0 = np.tile(_region_centre(cal), (len(df), 1))
            click.echo("starting joints: the centre of the covered joint ranges (no joint columns)")
        what = f"{point} targets"
    elif q0 is not None:
        point = point or "flange"
        T = nominal_targets(cal, q0, point)
        what = f"a joint program on the nominal model ({point} poses)"
    else:
        raise BadInput(
            f"{targets_path}: neither target columns (x, y, z[, qx, qy, qz, qw]) nor joint "
            f"columns ({', '.join(cal.joint_names)})"
        )
    payload = payload_column(df, targets_path, payload_kg)
    out = compensate_rows(cal, T, q0, point, payload)
    write_rows(out_path, out, "compensated", "compensate")
    _say(cal, out, what)
    click.echo(f"wrote {len(out)} compensated joint vectors to {out_path}")


def _region_centre(cal: Calibration) -> np.ndarray:
    """The middle of the covered ranges (0 where a range is unknown)."""
    import numpy as np

    lo, hi = cal.lower, cal.upper
    mid = 0.5 * (lo + hi)
    return np.where(np.isfinite(mid), mid, 0.0)


def _say(cal: Calibration, out: pd.DataFrame, what: str) -> None:
    """The console summary of a compensation."""
    import numpy as np

    from pipeline.io.numfmt import fmt
    from pipeline.use.tables import region_line

    res = out["residual_m"].to_numpy(dtype=float) * 1e3
    conv = out["converged"].to_numpy(dtype=bool)
    limits = out["within_limits"].to_numpy(dtype=bool)
    click.echo(f"model {cal.model}: {len(res)} {what}")
    click.echo(
        f"reached {int(conv.sum())} of {len(conv)} (largest residual {fmt(float(np.max(res)))} mm"
        + ("" if conv.all() else "; the rest are out of reach: converged false")
        + ")"
    )
    if not limits.all():
        click.echo(
            f"{int((~limits).sum())} rows outside the URDF's joint limits (within_limits false)"
        )
    click.echo(region_line(out))
