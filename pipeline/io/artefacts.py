"""Artefact schemas and atomic Parquet I/O: the one place artefacts touch the disk.

Every Parquet artefact has a schema declared once, as JSON in the top-level
``schemas/`` folder (``schemas/NAME.json``)::

    {
      "name": "touchups",
      "doc": "one row per touch-up ...",
      "columns": [
        {"name": "touchup_id", "type": "int64", "nullable": false, "unit": "", "doc": "..."},
        ...
      ],
      "extra_columns": {"type": "float64", "doc": "one column per joint, rad"}
    }

``type`` is one of :data:`TYPES`. ``extra_columns`` (or ``null``) admits further
columns of one type (e.g. one per URDF joint). Tables are validated on write and
on read; a write goes to a temporary file in the same folder and is renamed
into place, so a killed run never leaves a half-written artefact. Parquet
key-value metadata carries the stage, the package version, a hash of the
stage's configuration and the hashes of its input artefacts (``vtcal.*`` keys).

File hashing and the atomic write itself live in :mod:`pipeline.io.fileio` (standard
library only, for the cache checks that must not load pandas) and are re-exported here.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline import __version__
from pipeline.errors import BadInput, VtcalError
from pipeline.io import resources
from pipeline.io.fileio import atomic_write_bytes, bytes_hash, config_hash, file_hash

__all__ = [
    "SCHEMA_DIR",
    "TYPES",
    "Column",
    "Schema",
    "SchemaError",
    "atomic_write_bytes",
    "config_hash",
    "file_hash",
    "load_schema",
    "read_artefact",
    "read_artefact_table",
    "read_meta",
    "table_meta",
    "write_artefact",
    "write_artefact_table",
]

SCHEMA_DIR = resources.SCHEMA_DIR

TYPES: dict[str, pa.DataType] = {
    "int64": pa.int64(),
    "int32": pa.int32(),
    "float64": pa.float64(),
    "bool": pa.bool_(),
    "string": pa.string(),
    "binary": pa.binary(),
    "list<float64>": pa.list_(pa.float64()),
    "list<int64>": pa.list_(pa.int64()),
    "list<string>": pa.list_(pa.string()),
}


class SchemaError(VtcalError):
    """An artefact does not match its declared schema."""

    exit_code = 2


@dataclass(frozen=True)
class Column:
    name: str
    type: str
    nullable: bool = False
    unit: str = ""
    doc: str = ""


@dataclass(frozen=True)
class Schema:
    """A declared artefact schema (see module docstring)."""

    name: str
    doc: str
    columns: tuple[Column, ...]
    extra_type: str | None = None
    extra_doc: str = ""

    @property
    def column_names(self) -> list[str]:
        return [c.name for c in self.columns]

    def arrow_schema(self, extra: list[str] | tuple[str, ...] = ()) -> pa.Schema:
        """Arrow schema: declared columns in order, then the ``extra`` ones."""
        fields = [pa.field(c.name, TYPES[c.type], nullable=c.nullable) for c in self.columns]
        if extra:
            if self.extra_type is None:
                raise SchemaError(f"artefact {self.name!r} admits no extra columns: {list(extra)}")
            fields += [pa.field(n, TYPES[self.extra_type]) for n in extra]
        return pa.schema(fields)

    def extra_names(self, names: list[str]) -> list[str]:
        declared = set(self.column_names)
        return [n for n in names if n not in declared]

    def to_table(self, df: pd.DataFrame) -> pa.Table:
        """Coerce a DataFrame to this schema (declared order, declared types).

        Raises
        ------
        SchemaError
            On a missing column, an undeclared extra column, or a value that does
            not convert to its declared type.
        """
        missing = [c for c in self.column_names if c not in df.columns]
        if missing:
            raise SchemaError(f"artefact {self.name!r}: missing columns {missing}")
        extra = self.extra_names([str(c) for c in df.columns])
        schema = self.arrow_schema(extra)
        arrays = []
        for f in schema:
            try:
                arrays.append(pa.array(_py_column(df[f.name]), type=f.type, from_pandas=True))
            except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
                raise SchemaError(f"artefact {self.name!r}: column {f.name!r}: {exc}") from exc
        table = pa.Table.from_arrays(arrays, schema=schema)
        self.validate(table)
        return table

    def validate(self, table: pa.Table) -> None:
        """Check column presence, types and nullability against the declaration."""
        for c in self.columns:
            if c.name not in table.column_names:
                raise SchemaError(f"artefact {self.name!r}: missing column {c.name!r}")
            got = table.schema.field(c.name).type
            if got != TYPES[c.type]:
                raise SchemaError(
                    f"artefact {self.name!r}: column {c.name!r} is {got}, declared {c.type}"
                )
            if not c.nullable and table.column(c.name).null_count:
                raise SchemaError(f"artefact {self.name!r}: column {c.name!r} has nulls")
        for n in self.extra_names(table.column_names):
            if self.extra_type is None:
                raise SchemaError(f"artefact {self.name!r}: undeclared column {n!r}")
            if table.schema.field(n).type != TYPES[self.extra_type]:
                raise SchemaError(
                    f"artefact {self.name!r}: extra column {n!r} is "
                    f"{table.schema.field(n).type}, declared {self.extra_type}"
                )


def _py_column(s: pd.Series) -> Any:
    """Values of a column in a form ``pa.array`` converts without surprises."""
    if s.dtype == object:
        return [list(v) if isinstance(v, np.ndarray) else v for v in s]
    return s.to_numpy()


@cache
def load_schema(name: str) -> Schema:
    """Read ``schemas/NAME.json``."""
    path = SCHEMA_DIR / f"{name}.json"
    if not path.exists():
        raise SchemaError(f"no schema declared for artefact {name!r} ({path})")
    raw = json.loads(path.read_text())
    cols = tuple(
        Column(
            name=c["name"],
            type=c["type"],
            nullable=bool(c.get("nullable", False)),
            unit=c.get("unit", ""),
            doc=c.get("doc", ""),
        )
        for c in raw["columns"]
    )
    for c in cols:
        if c.type not in TYPES:
            raise SchemaError(f"schema {name!r}: column {c.name!r} has unknown type {c.type!r}")
    extra = raw.get("extra_columns")
    return Schema(
        name=raw["name"],
        doc=raw.get("doc", ""),
        columns=cols,
        extra_type=extra["type"] if extra else None,
        extra_doc=extra.get("doc", "") if extra else "",
    )


def write_artefact(
    path: str | os.PathLike[str],
    data: pd.DataFrame | pa.Table,
    schema: str,
    *,
    stage: str,
    config: Mapping[str, Any] | None = None,
    inputs: Mapping[str, str] | None = None,
    extra_meta: Mapping[str, str] | None = None,
) -> str:
    """Validate and atomically write a Parquet artefact; return its file hash.

    Parameters as :func:`write_artefact_table`.
    """
    return write_artefact_table(
        path, data, schema, stage=stage, config=config, inputs=inputs, extra_meta=extra_meta
    )[0]


def write_artefact_table(
    path: str | os.PathLike[str],
    data: pd.DataFrame | pa.Table,
    schema: str,
    *,
    stage: str,
    config: Mapping[str, Any] | None = None,
    inputs: Mapping[str, str] | None = None,
    extra_meta: Mapping[str, str] | None = None,
) -> tuple[str, pa.Table]:
    """Validate and atomically write a Parquet artefact; its file hash and the Arrow table
    written (checked, with its metadata: what :func:`read_artefact_table` reads back).

    Parameters
    ----------
    path : destination ``.parquet``
    data : the rows (DataFrame is coerced to the declared types)
    schema : name of the declared schema (``schemas/NAME.json``)
    stage : name of the stage that made it
    config : the stage's configuration (hashed into ``vtcal.config_hash``)
    inputs : ``{artefact name: file hash}`` of what the stage read
    extra_meta : further ``vtcal.*`` string metadata (e.g. joint names as JSON)
    """
    sch = load_schema(schema)
    table = sch.to_table(data) if isinstance(data, pd.DataFrame) else data
    sch.validate(table)
    meta = {
        b"vtcal.artefact": schema.encode(),
        b"vtcal.stage": stage.encode(),
        b"vtcal.version": __version__.encode(),
        b"vtcal.config_hash": config_hash(config or {}).encode(),
        b"vtcal.inputs": json.dumps(dict(inputs or {}), sort_keys=True).encode(),
    }
    for k, v in (extra_meta or {}).items():
        meta[f"vtcal.{k}".encode()] = str(v).encode()
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    blob = sink.getvalue().to_pybytes()
    atomic_write_bytes(path, blob)
    return bytes_hash(blob), table  # the file's hash (in a write group the file lands later)


def read_artefact_table(path: str | os.PathLike[str], schema: str) -> pa.Table:
    """Read and validate a Parquet artefact as an Arrow table."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as exc:
        raise BadInput(f"{path}: not a readable Parquet artefact: {exc}") from exc
    try:
        load_schema(schema).validate(table)
    except SchemaError as exc:
        raise SchemaError(f"{path}: {exc}") from exc
    return table


def read_artefact(path: str | os.PathLike[str], schema: str) -> pd.DataFrame:
    """Read and validate a Parquet artefact as a DataFrame."""
    return read_artefact_table(path, schema).to_pandas()


def read_meta(path: str | os.PathLike[str]) -> dict[str, str]:
    """The ``vtcal.*`` metadata of an artefact, keys without the prefix."""
    return table_meta(pq.read_schema(path))


def table_meta(schema: pa.Schema) -> dict[str, str]:
    """:func:`read_meta` of a table's ``schema``."""
    md = schema.metadata or {}
    return {
        k.decode()[len("vtcal.") :]: v.decode() for k, v in md.items() if k.startswith(b"vtcal.")
    }
