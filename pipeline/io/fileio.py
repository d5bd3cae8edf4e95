"""File hashing and atomic writes, with the standard library alone.

Kept apart from :mod:`pipeline.io.artefacts` (which loads pandas and pyarrow) so
that the run ledger and the orchestrator's cache checks can hash and write files
without importing any numeric library. :mod:`pipeline.io.artefacts` re-exports
these functions.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
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


def bytes_hash(data: bytes) -> str:
    """:func:`file_hash` of a file holding ``data``, without the file."""
    return hashlib.sha256(data).hexdigest()[:16]


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


def atomic_write_bytes(
    path: str | os.PathLike[str], data: bytes, *, mode: int | None = None
) -> None:
    """Write a file through a temporary sibling and ``os.replace`` (all or nothing).

    The temporary file is ``fsync``-ed before it replaces ``path``; it gets ``mode``
    (default: the usual mode a new file gets, ``0o666`` less the umask). Inside
    :func:`write_group` the file lands when the group ends (see there).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    if mode is None:
        mode = 0o666 & ~_UMASK  # mkstemp makes 0600; give the usual file mode
    groups = _groups()
    if groups:
        groups[-1].add(Path(tmp), path, mode, lambda: _write_fd(fd, data))
        return
    try:
        _write_fd(fd, data)
        _land(Path(tmp), path, mode)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def commit_file(tmp: Path, path: Path, mode: int) -> None:
    """Move a finished temporary file ``tmp`` (a sibling of ``path``) into place, durably.

    ``fsync`` it, give it ``mode``, then ``os.replace``: what :func:`atomic_write_bytes`
    does after writing, for a file another writer made (the Rerun SDK's ``run.rrd``),
    without copying its bytes. Inside :func:`write_group` it lands when the group ends.
    On error ``tmp`` is removed.
    """
    groups = _groups()
    if groups:
        groups[-1].add(tmp, path, mode, lambda: _fsync_path(tmp))
        return
    try:
        _fsync_path(tmp)
        _land(tmp, path, mode)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_fd(fd: int, data: bytes) -> None:
    """Write ``data`` to the open file ``fd``, ``fsync`` it and close it."""
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _land(tmp: Path, path: Path, mode: int) -> None:
    os.chmod(tmp, mode)
    os.replace(tmp, path)


class _Group:
    """The files of one :func:`write_group`, written and ``fsync``-ed in threads."""

    def __init__(self) -> None:
        self.pool = ThreadPoolExecutor(max_workers=8, thread_name_prefix="vtcal-fsync")
        self.files: list[tuple[Path, Path, int, Future[None]]] = []

    def add(self, tmp: Path, path: Path, mode: int, work: Callable[[], None]) -> None:
        self.files.append((tmp, path, mode, self.pool.submit(work)))

    def finish(self, land: bool) -> None:
        """Wait for every file's write; move them into place in order when ``land``
        (else, or when one failed, remove every temporary file and raise the failure)."""
        error: BaseException | None = None
        for _, _, _, fut in self.files:
            exc = fut.exception()
            error = error or exc
        self.pool.shutdown()
        try:
            if land and error is None:
                for tmp, path, mode, _ in self.files:
                    _land(tmp, path, mode)
        finally:
            for tmp, _, _, _ in self.files:
                tmp.unlink(missing_ok=True)
        if land and error is not None:
            raise error


#: per thread, the open write groups, innermost last (:func:`write_group`)
_LOCAL = threading.local()


def _groups() -> list[_Group]:
    groups: list[_Group] | None = getattr(_LOCAL, "groups", None)
    if groups is None:
        groups = _LOCAL.groups = []
    return groups


@contextmanager
def write_group() -> Iterator[None]:
    """Files written inside land together: each durable, in the order written.

    Every :func:`atomic_write_bytes` (and :func:`commit_file`) inside writes its
    temporary sibling and ``fsync``-s it in a thread; when the block ends, the
    writes are waited for and the files moved into place in the order they were
    written (so "the last file present means its writer finished" still holds).
    The ``fsync``-s of a group overlap, and the file system commits them together:
    the identify stage's nine files no longer wait for nine commits one after another
    when the disk is busy (``benchmarks/bench_write_group.py``, docs/speed.md: on a
    quiet disk an ``fsync`` is cheap and the group changes little). Inside the block a
    written path still holds its previous
    content (or does not exist), so nothing inside may read back what it wrote. When the
    block raises, or a write fails, none of its files land (their temporaries are removed).
    Groups nest (an inner group's files land when it ends); a group holds the writes of
    the thread that opened it.
    """
    group = _Group()
    _groups().append(group)
    ok = False
    try:
        yield
        ok = True
    finally:
        _groups().remove(group)
        group.finish(ok)
