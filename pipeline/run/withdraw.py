"""Withdraw what a refused run wrote: nothing partial is left in a run folder.

A run that ends in a refusal (a :class:`~pipeline.errors.VtcalError`: bad
input, exit 2, or a calibration that cannot be trusted, exit 3) must not leave
the artefacts of its first stages (``frames``, ``detections``,
``recording.json``) in ``--out`` as if they were a result. The orchestrator
takes a :func:`snapshot` of the folder before the stages run, and on a
refusal :func:`withdraw` removes every file the run created, puts back the
files it rewrote as they were, and removes the folder itself when the run
created it. Files that were there before and that the run did not touch (a
previous run's cached artefacts) stay. So a forced re-run of a finished run
folder that is refused leaves the previous run whole, not a mix of its
calibration and nothing under it.

Putting back: :func:`snapshot` hard-links every file directly in the folder
(where a run writes; not those of subfolders) into :data:`BACKUP` inside it (no copy; every artefact is written through
a temporary and ``os.replace``, so a rewrite gives the path a new file and
the link keeps the old one); :func:`release` drops the links when the run
ends any other way. Where the file system has no hard links, a rewritten file
is removed as before (named in the docstring of :func:`withdraw`).
An interrupted run (Ctrl-C, a kill) is not a refusal: its finished artefacts
stay, so the next run resumes (docs/robustness.md, "Interrupted runs").
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

#: a file's identity for "did this run touch it": (size, modification time in ns)
Stamp = tuple[int, int]

#: the folder, inside the run folder, of the hard links :func:`snapshot` keeps
BACKUP = ".vtcal-before"


def _files(folder: Path) -> dict[Path, Stamp]:
    out: dict[Path, Stamp] = {}
    for p in folder.rglob("*"):
        try:
            if BACKUP not in p.relative_to(folder).parts and p.is_file():
                st = p.stat()
                out[p] = (st.st_size, st.st_mtime_ns)
        except OSError:
            continue
    return out


def snapshot(folder: Path, keep: bool = True) -> dict[Path, Stamp] | None:
    """Every file under ``folder`` with its :data:`Stamp`; None when the folder does not exist.

    With ``keep``, each file directly in ``folder`` (where a run writes its artefacts;
    not the files of subfolders) is also hard-linked into ``folder / BACKUP`` (a stale
    one, from a run that was killed, is dropped first), so :func:`withdraw` can put it
    back.
    """
    if not folder.is_dir():
        return None
    release(folder)
    out = _files(folder)
    if keep:
        for p in out:
            if p.parent != folder:
                continue
            dst = folder / BACKUP / p.name
            try:
                dst.parent.mkdir(exist_ok=True)
                os.link(p, dst)
            except OSError:  # no hard links here: withdraw removes a rewritten file
                continue
    return out


def release(folder: Path) -> None:
    """Drop the hard links :func:`snapshot` kept (the run ended without a refusal)."""
    shutil.rmtree(folder / BACKUP, ignore_errors=True)


def withdraw(folder: Path, before: dict[Path, Stamp] | None) -> list[Path]:
    """Remove the files under ``folder`` that are new, put back the ones rewritten since
    ``before`` (from :func:`snapshot`'s links; removed when there is no link).

    Folders left empty are removed too (``folder`` itself only when ``before``
    is None: the run created it). Returns the files removed or put back.
    """
    if not folder.is_dir():
        return []
    now = _files(folder)
    old = before or {}
    removed = [p for p, st in now.items() if old.get(p) != st]
    # a file the run deleted: put back too (not a killed run's hidden temporary)
    removed += [p for p in old if p not in now and not p.name.startswith(".")]
    for p in removed:
        kept = folder / BACKUP / p.name
        if p in old and p.parent == folder and kept.is_file():
            os.replace(kept, p)
        else:
            p.unlink(missing_ok=True)
    release(folder)
    dirs = sorted((d for d in folder.rglob("*") if d.is_dir()), key=lambda d: -len(d.parts))
    for d in [*dirs, *([folder] if before is None else [])]:
        try:
            d.rmdir()  # only when empty
        except OSError:
            pass
    return removed
