"""The disk edge of ``vtcal predict`` and ``vtcal compensate``: their tables in and out.

In: CSV (UTF-8 or UTF-16 with a BOM; comma, semicolon or tab) or Parquet, read
by :func:`pipeline.commands.identify.read_table`; columns named by the URDF's
joints (rad), checked here: a missing joint or a value that is not a finite
number is one line naming the file, the row and the column.

Out: the declared schemas ``schemas/predictions.json`` and
``schemas/compensated.json``, checked on write, written all-or-nothing
(Parquet for ``.parquet`` / ``.pq``, CSV otherwise): an existing file is replaced only
by a complete one.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.errors import BadInput


def read_rows(path: Path) -> pd.DataFrame:
    """A table of joint vectors or targets (CSV or Parquet), as the user wrote it."""
    from pipeline.io.tables import read_table

    return read_table(path, "table")


def joint_matrix(
    df: pd.DataFrame, joints: list[str], path: Path, required: bool = True
) -> np.ndarray | None:
    """The (N, n) joint columns of ``df`` (rad), in ``joints`` order.

    ``required=False``: None when the table has none of them. Raises BadInput on
    a missing joint column, a value that is not a number or not finite.
    """
    have = [j for j in joints if j in df.columns]
    if not have and not required:
        return None
    missing = [j for j in joints if j not in df.columns]
    if missing:
        raise BadInput(
            f"{path}: no column for joint(s) {missing}; the robot's joints are {joints} "
            f"(the table has {list(df.columns)[:12]})"
        )
    return finite_columns(df, joints, path)


def finite_columns(df: pd.DataFrame, cols: list[str], path: Path) -> np.ndarray:
    """``df[cols]`` as floats; BadInput naming the first row and column that is not finite."""
    values = df[cols].apply(pd.to_numeric, errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if bad.any():
        i, j = (int(v[0]) for v in np.nonzero(bad))
        raise BadInput(
            f"{path}: row {i}, column {cols[j]!r}: {df[cols[j]].iloc[i]} is not a finite number"
        )
    return values


def payload_column(df: pd.DataFrame, path: Path, default: float | None) -> np.ndarray:
    """Per row the payload (kg): the ``payload_kg`` column, else ``default`` (NaN: none given)."""
    if "payload_kg" in df.columns:
        kg = finite_columns(df, ["payload_kg"], path)[:, 0]
        if (kg < 0).any():
            i = int(np.flatnonzero(kg < 0)[0])
            raise BadInput(f"{path}: row {i}, column 'payload_kg': {kg[i]} kg is negative")
        return kg
    return np.full(len(df), np.nan if default is None else float(default))


def write_rows(path: Path, df: pd.DataFrame, schema: str, stage: str) -> None:
    """Write ``df`` to ``path`` under the declared ``schema`` (Parquet or CSV), all or nothing."""
    from pipeline.io.artefacts import load_schema, write_artefact
    from pipeline.io.fileio import atomic_write_bytes
    from pipeline.io.tables import PARQUET_SUFFIXES

    if path.suffix.lower() in PARQUET_SUFFIXES:
        write_artefact(path, df, schema, stage=stage)
        return
    sch = load_schema(schema)
    sch.validate(sch.to_table(df))
    buf = io.StringIO()
    df.to_csv(buf, index=False, float_format="%.17g")
    atomic_write_bytes(path, buf.getvalue().encode())
