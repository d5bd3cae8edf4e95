"""Withdraw what a refused run wrote: nothing partial is left in a run folder.

A run that ends in a refusal (a :class:`~pipeline.errors.VtcalError`: bad
input, exit 2, or a calibration that cannot be trusted, exit 3) must not leave
the artefacts of its first stages (``frames``, ``detections``,
``recording.json``) in ``--out`` as if they were a result. The orchestrator
takes a :func:`snapshot` of the folder before the stages run, and on a
refusal :func:`withdraw` removes every file the run created or rewrote, and
the folder itself when the run created it. Files that were there before and
that the run did not touch (a previous run's cached artefacts) stay.
An interrupted run (Ctrl-C, a kill) is not a refusal: its finished artefacts
stay, so the next run resumes (docs/robustness.md, "Interrupted runs").
"""

from __future__ import annotations

from pathlib import Path

#: a file's identity for "did this run touch it": (size, modification time in ns)
Stamp = tuple[int, int]


def snapshot(folder: Path) -> dict[Path, Stamp] | None:
    """Every file under ``folder`` with its :data:`Stamp`; None when the folder does not exist."""
    if not folder.is_dir():
        return None
    out: dict[Path, Stamp] = {}
    for p in folder.rglob("*"):
        try:
            if p.is_file():
                st = p.stat()
                out[p] = (st.st_size, st.st_mtime_ns)
        except OSError:
            continue
    return out


def withdraw(folder: Path, before: dict[Path, Stamp] | None) -> list[Path]:
    """Remove the files under ``folder`` that are new or changed since ``before``.

    Folders left empty are removed too (``folder`` itself only when ``before``
    is None: the run created it). Returns the removed files.
    """
    now = snapshot(folder)
    if now is None:
        return []
    old = before or {}
    removed = [p for p, st in now.items() if old.get(p) != st]
    for p in removed:
        p.unlink(missing_ok=True)
    dirs = sorted((d for d in folder.rglob("*") if d.is_dir()), key=lambda d: -len(d.parts))
    for d in [*dirs, *([folder] if before is None else [])]:
        try:
            d.rmdir()  # only when empty
        except OSError:
            pass
    return removed
