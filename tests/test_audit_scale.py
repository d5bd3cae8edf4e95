"""The audit at scale: on the batch's engines (serial, processes, Dask) and incremental.

Touch-up-level histories (:mod:`pipeline.sim.history`, 6 touch-ups per target): the
tables must be equal wherever the fits ran, and an audit run again into the same
folder fits only the recordings it has not seen.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from pipeline.audit.audit import AuditResult, run_audit
from pipeline.audit.identity import load_item, run_folders
from pipeline.sim.history import make_history, write_history

ROOT = Path(__file__).resolve().parent.parent
MODELS = ("offsets", "full")
ROBOTS = 3


def _fleet(folder: Path, n_recordings: int, only_last: bool = False) -> None:
    for r in range(ROBOTS):
        hist = make_history(f"R{r}", n_recordings=n_recordings, seed=40 + r, per_target=6)
        write_history(hist[-1:] if only_last else hist, folder)


def _audit(runs: Path, **kw: object) -> AuditResult:
    items = [load_item(f, table=False) for f in run_folders([runs])]
    return run_audit(items, models=MODELS, **kw)  # type: ignore[arg-type]


def _equal(a: AuditResult, b: AuditResult) -> None:
    for name in ("recordings", "changes", "models", "ranking"):
        pd.testing.assert_frame_equal(getattr(a, name), getattr(b, name), check_exact=True)
    assert a.lines == b.lines


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fleet")
    _fleet(folder, 3)
    return folder


@pytest.fixture(scope="module")
def serial(runs: Path) -> AuditResult:
    return _audit(runs, workers=1)


def test_two_processes_give_the_serial_tables(runs: Path, serial: AuditResult) -> None:
    _equal(serial, _audit(runs, workers=2, executor="processes"))
    assert serial.counts == {"fits": (9, 0), "held-out": (18, 0), "comparisons": (8, 0)}


def test_a_local_dask_cluster_gives_the_serial_tables(runs: Path, serial: AuditResult) -> None:
    pytest.importorskip("distributed")
    _equal(serial, _audit(runs, workers=2, executor="dask"))


def test_the_audit_folder_is_a_cache(tmp_path: Path, serial: AuditResult, runs: Path) -> None:
    import shutil

    shutil.copytree(runs, tmp_path / "runs")
    out = tmp_path / "audit"
    first = _audit(tmp_path / "runs", workers=1, cache_dir=out)
    _equal(serial, first)
    again = _audit(tmp_path / "runs", workers=1, cache_dir=out)
    assert again.counts == {"fits": (0, 9), "held-out": (0, 18), "comparisons": (0, 8)}
    _equal(serial, again)
    assert again.estimates["R0-r01"].names == first.estimates["R0-r01"].names
    # one more recording per robot: only those are fitted and compared
    _fleet(tmp_path / "runs", 4, only_last=True)
    more = _audit(tmp_path / "runs", workers=2, cache_dir=out)
    assert more.counts == {"fits": (3, 9), "held-out": (6, 18), "comparisons": (3, 8)}
    _equal(_audit(tmp_path / "runs", workers=1), more)
    # a damaged entry and a missing one are computed again, nothing else
    fits = sorted((out / "cache" / "fit").rglob("*.pkl"))
    fits[0].write_bytes(fits[0].read_bytes()[:-10] + b"0123456789")
    fits[1].unlink()
    held = sorted((out / "cache" / "heldout").rglob("*.pkl"))
    held[0].write_bytes(b"")
    fixed = _audit(tmp_path / "runs", workers=1, cache_dir=out)
    assert fixed.counts["fits"] == (2, 10) and fixed.counts["held-out"] == (1, 23)
    _equal(more, fixed)
    # other options: alpha changes no fit, only the comparisons
    other = _audit(tmp_path / "runs", workers=1, cache_dir=out, alpha=0.05)
    assert other.counts == {"fits": (0, 12), "held-out": (0, 24), "comparisons": (11, 0)}


def _vtcal(*args: str) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, env=env
    )


def test_cli_counts_its_work_and_takes_the_batch_options(runs: Path, tmp_path: Path) -> None:
    out = tmp_path / "audit"
    args = ("audit", str(runs), "--out", str(out), "--models", ",".join(MODELS))
    p = _vtcal(*args, "--workers", "2")
    assert p.returncode == 0, p.stderr
    assert "fits: 9 new, 0 cached; held-out: 18 new, 0 cached; comparisons: 8 new" in p.stdout
    p = _vtcal(*args, "--workers", "1")
    assert p.returncode == 0, p.stderr
    assert "fits: 0 new, 9 cached; held-out: 0 new, 18 cached; comparisons: 0 new" in p.stdout
    bad = _vtcal(*args, "--scheduler", "tcp://127.0.0.1:1")
    assert bad.returncode != 0 and "--scheduler is for --executor dask" in bad.stderr
