"""JSON side files of a run folder: one byte-stable form (sorted keys, one-space indent).

Standard library only (numpy values are converted when numpy is loaded).
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.io.fileio import atomic_write_bytes


def jsonable(obj: Any) -> Any:
    """JSON form of configs and summaries; numpy arrays (bulk data) are left out."""
    np = sys.modules.get("numpy")  # not loaded: nothing here can be a numpy value

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: jsonable(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            if np is None or not isinstance(getattr(obj, f.name), np.ndarray)
        }
    if np is not None and isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def json_bytes(obj: Any) -> bytes:
    """The bytes of a JSON side file (sorted keys, one-space indent: byte-stable)."""
    return (json.dumps(jsonable(obj), indent=1, sort_keys=True) + "\n").encode()


def write_json(path: Path, obj: Any) -> None:
    """Atomically write a JSON side file (:func:`json_bytes`)."""
    atomic_write_bytes(path, json_bytes(obj))
