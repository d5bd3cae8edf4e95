"""Write groups (pipeline.io.fileio.write_group): a stage's files fsync-ed together, landing in order."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from pipeline.io import fileio
from pipeline.run.orchestrator import RunConfig, run_pipeline

SAMPLE = Path(__file__).resolve().parents[1] / "datasets" / "samples" / "sample_lrmate.mcap"


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    out = tmp_path_factory.mktemp("write_group") / "run"
    run_pipeline(SAMPLE, out, RunConfig(report=False), until="identify")
    return out


class _SlowFsync:
    """``os.fsync`` that takes ``delay`` s and records how many ran at once."""

    def __init__(self, delay: float = 0.02) -> None:
        self.delay, self.now, self.most, self.calls = delay, 0, 0, 0
        self.lock = threading.Lock()
        self.real = os.fsync

    def __call__(self, fd: int) -> None:
        with self.lock:
            self.now += 1
            self.calls += 1
            self.most = max(self.most, self.now)
        try:
            time.sleep(self.delay)
            self.real(fd)
        finally:
            with self.lock:
                self.now -= 1


def test_a_group_lands_its_files_in_order_when_it_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    slow = _SlowFsync()
    monkeypatch.setattr(os, "fsync", slow)
    landed: list[str] = []
    real_replace = os.replace

    def replace(src: str, dst: str) -> None:
        landed.append(Path(dst).name)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    (tmp_path / "b.json").write_bytes(b"old")
    with fileio.write_group():
        for name in ("a.parquet", "b.json", "c.urdf"):
            fileio.atomic_write_bytes(tmp_path / name, name.encode())
        assert not (tmp_path / "a.parquet").exists()  # nothing lands before the group ends
        assert (tmp_path / "b.json").read_bytes() == b"old"
    assert landed == ["a.parquet", "b.json", "c.urdf"]
    assert [(tmp_path / n).read_bytes() for n in landed] == [n.encode() for n in landed]
    assert slow.calls == 3 and slow.most > 1  # fsync-ed at once, not one after another
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(landed)  # no temporaries


def test_a_group_that_raises_lands_nothing(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_bytes(b"old")
    with pytest.raises(RuntimeError, match="stage failed"), fileio.write_group():
        fileio.atomic_write_bytes(tmp_path / "a.json", b"new")
        fileio.atomic_write_bytes(tmp_path / "b.json", b"new")
        raise RuntimeError("stage failed")
    assert (tmp_path / "a.json").read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_commit_file_moves_a_finished_file_into_place(tmp_path: Path) -> None:
    tmp = tmp_path / ".run.rrd.partial"
    tmp.write_bytes(b"rrd")
    fileio.commit_file(tmp, tmp_path / "run.rrd", 0o644)
    assert (tmp_path / "run.rrd").read_bytes() == b"rrd" and not tmp.exists()
    assert (tmp_path / "run.rrd").stat().st_mode & 0o777 == 0o644


def test_the_identify_stage_fsyncs_its_files_together(
    sample_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its three tables, models.json and a URDF per model: nine files, not nine waits."""
    out = tmp_path / "run"
    shutil.copytree(sample_run, out)
    cfg = RunConfig(report=False, stage_options={"identify": {"workers": 1}})
    (out / "parameters.parquet").unlink()
    slow = _SlowFsync()
    monkeypatch.setattr(os, "fsync", slow)
    res = run_pipeline(SAMPLE, out, cfg, until="identify")
    assert {s.stage: s.status for s in res.stages}["identify"] == "ran"
    assert (out / "parameters.parquet").exists()
    assert slow.most >= 4  # the old runner fsync-ed them one after another (most == 1)
