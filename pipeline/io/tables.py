"""Tables a user writes (touch-ups, joint values, targets): CSV or Parquet, read once here.

CSV in UTF-8 (with or without a BOM) or UTF-16 with a BOM, comma, semicolon or
tab separated (the separator the header uses most); Parquet by suffix. A file
that is not such a table is one line naming it and what is wrong.
"""

from __future__ import annotations

import io
from pathlib import Path

import pandas as pd

from pipeline.errors import BadInput

#: suffixes read and written as Parquet (anything else a table reader takes is CSV)
PARQUET_SUFFIXES = (".parquet", ".pq")


def read_table(path: Path, what: str = "touch-up table") -> pd.DataFrame:
    """A table from ``.csv`` or ``.parquet``; ``what`` names it in the errors.

    Raises
    ------
    BadInput
        Unknown suffix, unreadable file, or an empty table.
    """
    suffix = path.suffix.lower()
    try:
        if suffix == ".csv":
            df = _read_csv(path)
        elif suffix in PARQUET_SUFFIXES:
            df = pd.read_parquet(path)
        else:
            raise BadInput(f"{path}: {what} must be .csv or .parquet, not {suffix!r}")
    except BadInput:
        raise
    except Exception as exc:  # pandas/pyarrow raise many types for a bad file
        raise BadInput(f"{path}: not a readable {what}: {exc}") from exc
    if df.empty:
        raise BadInput(f"{path}: the {what} has no rows")
    return df


def _read_csv(path: Path) -> pd.DataFrame:
    """A CSV in UTF-8 (BOM or not) or UTF-16 with a BOM; comma, semicolon or tab separated.

    Raises BadInput naming the first byte that is not text.
    """
    raw = path.read_bytes()
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        encoding = "utf-16"
    else:
        encoding = "utf-8-sig"
    try:
        text = raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise BadInput(
            f"{path}: not a text CSV: byte 0x{raw[exc.start]:02x} at offset {exc.start} is not "
            f"{encoding.upper().replace('-SIG', '')} (save the table as UTF-8 CSV)"
        ) from exc
    if "\x00" in text:
        raise BadInput(f"{path}: not a text CSV: it holds NUL characters (binary data?)")
    first = text.split("\n", 1)[0]
    sep = max((",", ";", "\t"), key=first.count)
    return pd.read_csv(io.StringIO(text), sep=sep)
