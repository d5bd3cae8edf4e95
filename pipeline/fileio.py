"""File hashing and atomic writes, with the standard library alone.

Kept apart from :mod:`pipeline.artefacts` (which loads pandas and pyarrow) so
that the run ledger and the orchestrator's cache checks can hash and write files
without importing any numeric library. :mod:`pipeline.artefacts` re-exports
these functions.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any


def config_hash(config: Mapping[str, Any]) -> str:
    """Stable short hash of a JSON-able configuration mapping."""
    blob = json.dumps(config, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def file_hash(path: str | os.PathLike[str]) -> str:
    """SHA-256 (first 16 hex digits) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def hash_named_files(h: Any, files: Iterable[tuple[str, Path]]) -> None:
    """Feed the hash ``h`` each file as ``name NUL length NUL bytes``, in the order given.

    Names go in with the contents, so a renamed, added or removed file changes the
    digest as an edited one does (the run ledger's and the stage cache keys' code digests).
    """
    for name, path in files:
        data = path.read_bytes()
        h.update(f"{name}\0{len(data)}\0".encode())
        h.update(data)


_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write a file through a temporary sibling and ``os.replace`` (all or nothing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
