"""A refused run leaves its run folder as it found it (pipeline.run.withdraw).

A forced re-run of a finished run folder rewrites its artefacts as it goes; when
a later stage refuses, the files it rewrote must come back as they were, not be
removed (which left a previous run's calibration with nothing under it).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from pipeline.cli import main
from pipeline.run.withdraw import BACKUP, release, snapshot, withdraw

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"


def digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def replace(path: Path, text: str) -> None:
    """Rewrite ``path`` as every artefact writer does: a temporary, then ``os.replace``."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def test_withdraw_puts_back_rewritten_and_deleted_files(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    for name in ("kept.txt", "rewritten.txt", "deleted.txt", "sub/deep.txt"):
        (tmp_path / name).write_text(f"before: {name}")
    want = digests(tmp_path)
    before = snapshot(tmp_path)
    replace(tmp_path / "rewritten.txt", "the refused run's")
    assert not (tmp_path / BACKUP / "sub").exists()  # a run writes no subfolder: not kept
    (tmp_path / "deleted.txt").unlink()
    (tmp_path / "new.txt").write_text("the refused run's")
    done = withdraw(tmp_path, before)
    assert digests(tmp_path) == want
    assert not (tmp_path / BACKUP).exists()
    assert {p.name for p in done} == {"rewritten.txt", "deleted.txt", "new.txt"}


def test_release_drops_the_links_and_keeps_the_run(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text("before")
    snapshot(tmp_path)
    assert (tmp_path / BACKUP / "a.txt").is_file()
    replace(tmp_path / "a.txt", "after")
    release(tmp_path)
    assert not (tmp_path / BACKUP).exists() and (tmp_path / "a.txt").read_text() == "after"


def exit_code(args: list[str]) -> int:
    try:
        main(args)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_a_refused_forced_rerun_leaves_the_previous_run_whole(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert exit_code(["run", str(SAMPLE), "--out", str(out), "--until", "touchups", "-q"]) == 0
    want = digests(out)
    assert {"frames.parquet", "detections.parquet", "touchups.parquet"} <= set(want)
    # no target 7: identify refuses (exit 2) after ingest and touchups were written again
    refused = ["run", str(SAMPLE), "--out", str(out), "--until", "identify", "--force", "-q"]
    assert exit_code([*refused, "--distance", "0:7=0.25"]) == 2
    assert digests(out) == want
