"""The run ledger: is a run folder already exactly what this request would make?

When a run finishes, ``run.json`` records under ``"ledger"`` a *fingerprint* of
the request and the content hash of every artefact that the stages which ran
or were cached hold in the run folder::

    "ledger": {
      "fingerprint": {"recording": HASH, "config": {...RunConfig...}, "until": null,
                      "version": "0.1.0", "code": HASH},
      "artefacts": {"frames.parquet": HASH, "identify.json": HASH, ...}
    }

The fingerprint holds the recording's content hash, the :class:`RunConfig` in
JSON form, ``until``, the package version and a digest of the code (every
``pipeline/**/*.py`` and ``schemas/**`` file, computed once per process). When
the same request comes again and every recorded artefact is still there with
its recorded hash, the run is complete as it stands: :func:`lookup` says so
without importing pandas, pyarrow or any stage module. Anything else (other
recording bytes, options, ``until`` or code; a missing, edited or corrupt
artefact; a temporary file a killed run left behind) is a miss, and the
orchestrator's per-stage checks decide what to redo.

Standard library only (plus the package version and :mod:`pipeline.io.fileio`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterable
from functools import cache
from pathlib import Path
from typing import Any

from pipeline import __version__
from pipeline.io import resources
from pipeline.io.fileio import file_hash, hash_named_files
from pipeline.io.layout import locate, recording_hash
from pipeline.io.run_folder import RUN_FILES

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # pipeline/ (this module is in pipeline/run/)
SCHEMA_DIR = resources.SCHEMA_DIR

#: key of the ledger entry in ``run.json``
KEY = "ledger"


@cache
def code_digest() -> str:
    """Digest of the code that makes a run: every ``pipeline/**/*.py`` and ``schemas/**`` file.

    Computed once per process (a few milliseconds). Paths are taken relative to
    the repository root and hashed with the contents, so a renamed, added or
    removed file changes the digest too.

    Returns
    -------
    str : 16 hex digits of SHA-256.
    """
    files = sorted(PACKAGE_DIR.rglob("*.py"))
    if SCHEMA_DIR.is_dir():
        files += sorted(p for p in SCHEMA_DIR.rglob("*") if p.is_file())
    h = hashlib.sha256()
    hash_named_files(h, ((p.relative_to(PACKAGE_DIR.parent).as_posix(), p) for p in files))
    return h.hexdigest()[:16]


def config_json(config: Any) -> Any:
    """JSON form of a run configuration (a dataclass of plain values, or None).

    Round-tripped through JSON so that a fingerprint compares equal to the one
    read back from ``run.json`` (tuples become lists, keys strings).
    """
    is_instance = dataclasses.is_dataclass(config) and not isinstance(config, type)
    raw = dataclasses.asdict(config) if is_instance else config
    return json.loads(json.dumps(raw, sort_keys=True, default=str))


def fingerprint(recording: Path, config: Any, until: str | None) -> dict[str, Any]:
    """The fingerprint of a run request (see module docstring).

    Parameters
    ----------
    recording : the MCAP file or ROS bag (hashed: its bytes, not its name, count;
        :func:`pipeline.io.layout.recording_hash`)
    config : the run's :class:`~pipeline.run.orchestrator.RunConfig`
    until : last stage asked for, or None
    """
    return {
        "recording": recording_hash(locate(recording)),
        "config": config_json(config),
        "until": until,
        "version": __version__,
        "code": code_digest(),
    }


def entry(out: Path, fp: dict[str, Any], outputs: Iterable[str]) -> dict[str, Any] | None:
    """The ledger entry of a finished run: ``fp`` and the hash of every output file.

    Returns None when an output the stages name is absent (nothing to vouch for).
    """
    arts: dict[str, str] = {}
    for name in sorted(set(outputs)):
        p = out / name
        if not p.is_file():
            return None
        arts[name] = file_hash(p)
    if not arts:
        return None
    return {"fingerprint": fp, "artefacts": arts}


def temporaries(out: Path) -> list[Path]:
    """Temporaries a killed run left in ``out`` (``.NAME.*.tmp``, ``.NAME.partial``).

    Never artefacts: a run folder has one run at a time, so they are stale.
    """
    return [*out.glob(".*.tmp"), *out.glob(".*.partial")]


def lookup(out: Path, fp: dict[str, Any]) -> dict[str, Any] | None:
    """The run record (``run.json``) of ``out`` when its ledger vouches for ``fp``.

    A hit needs: ``run.json`` readable with a ledger entry whose fingerprint
    equals ``fp``; every artefact it lists present with its recorded hash; no
    temporary file left by a killed run; and a stage list to report.

    Returns
    -------
    dict or None : the parsed ``run.json`` on a hit, None on any miss.
    """
    try:
        run = json.loads((out / RUN_FILES["run"]).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(run, dict):
        return None
    led = run.get(KEY)
    stages = run.get("stages")
    if not isinstance(led, dict) or led.get("fingerprint") != fp:
        return None
    arts = led.get("artefacts")
    if not isinstance(arts, dict) or not arts or not isinstance(stages, list) or not stages:
        return None
    if not all(isinstance(s, dict) and isinstance(s.get("stage"), str) for s in stages):
        return None
    if temporaries(out):
        return None
    for name, want in arts.items():
        p = out / str(name)
        if Path(str(name)).name != name or not p.is_file():
            return None
        try:
            if file_hash(p) != want:
                return None
        except OSError:
            return None
    return run
