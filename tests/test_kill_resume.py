"""Interrupted runs: SIGKILL / SIGINT at seeded random moments never leave a partial artefact.

``vtcal run`` on the sample is started in a subprocess and killed several times
in the same run folder (alternately SIGKILL, the recorder-killed case, and
SIGINT, Ctrl-C). After every kill each ``*.parquet`` present must validate
against its schema, each JSON side file must parse, and nothing but hidden
temporaries (``.NAME.*.tmp``, ``.run.rrd.partial``) may be incomplete (a
SIGKILL also leaves ``.vtcal-before/``, the run's links to the files it found).
A last uninterrupted run resumes (stages finished before a kill are cached),
removes those temporaries and ends with Parquet artefacts byte-identical to a
clean run's.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.io.artefacts import read_artefact
from pipeline.run.withdraw import BACKUP

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
SCHEMA_OF = {
    "frames.parquet": "frames",
    "detections.parquet": "detections",
    "touchups.parquet": "touchups",
    "inliers.parquet": "inliers",
    "parameters.parquet": "parameters",
    "residuals.parquet": "residuals",
    "targets.parquet": "targets",
    "crossval.parquet": "crossval",
}
N_KILLS = 8


def _vtcal(out: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline", "run", str(SAMPLE), "--out", str(out), "-q", *extra],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONHASHSEED": "0"},
    )


def _check_folder(out: Path) -> list[str]:
    """Every artefact present is whole; returns the hidden temporaries found."""
    for p in out.iterdir():
        name = p.name
        if name == BACKUP:  # a killed run's links to the files it found (pipeline.run.withdraw)
            assert p.is_dir() and all(q.parent == p for q in p.iterdir()), name
            continue
        if name.startswith("."):
            assert name.endswith((".tmp", ".partial")), name
            continue
        assert not name.endswith((".tmp", ".partial")), f"visible temporary {name}"
        if name.endswith(".parquet"):
            assert name in SCHEMA_OF, name
            read_artefact(p, SCHEMA_OF[name])  # raises on a partial or foreign file
        elif name.endswith(".json"):
            json.loads(p.read_text())
        elif name.endswith(".urdf"):
            assert p.read_text().rstrip().endswith("</robot>"), name
        elif name == "report.html":
            assert p.read_text().rstrip().endswith("</html>")
    return sorted(p.name for p in out.iterdir() if p.name.startswith("."))


def test_killed_runs_leave_no_partial_artefact_and_resume(tmp_path: Path) -> None:
    ref = tmp_path / "clean"
    t0 = time.perf_counter()
    p = _vtcal(ref)
    _, err = p.communicate(timeout=600)
    assert p.returncode == 0, err.decode()
    t_full = time.perf_counter() - t0

    rng = np.random.default_rng(20261122)
    out = tmp_path / "killed"
    leftovers: list[str] = []
    log = []
    for i in rng.permutation(N_KILLS).tolist():
        sig = signal.SIGKILL if i % 2 == 0 else signal.SIGINT
        # half the runs --force: a kill then also hits the overwrite of existing artefacts
        force = i % 4 < 2
        # stratified over the run: one random moment in each 1/N of a clean run's duration
        when = float(t_full * (i + rng.uniform()) / N_KILLS)
        p = _vtcal(out, *(["--force"] if force else []))
        try:
            p.wait(timeout=when)
        except subprocess.TimeoutExpired:
            p.send_signal(sig)
        _, err = p.communicate(timeout=120)
        text = err.decode()
        log.append((sig.name, "force" if force else "resume", round(when, 1), p.returncode))
        if p.returncode == 130:  # SIGINT caught by vtcal: one line, no traceback
            assert "Traceback" not in text and "interrupted" in text, text
        elif p.returncode != 0:
            # -SIGINT: Ctrl-C during interpreter shutdown, after every artefact was written
            assert p.returncode in (-signal.SIGKILL, -signal.SIGINT), (p.returncode, text)
        if out.exists():
            leftovers += _check_folder(out)

    had_frames = (out / "frames.parquet").exists()
    p = _vtcal(out)
    _, err = p.communicate(timeout=600)
    assert p.returncode == 0, err.decode()
    assert _check_folder(out) == [], "temporaries of killed runs not cleaned up"
    run = json.loads((out / "run.json").read_text())
    status = {s["stage"]: s["status"] for s in run["stages"]}
    print(f"kills (signal, mode, s, exit): {log}; temporaries left by kills: {leftovers}; "
          f"final run: {status}")  # fmt: skip
    if had_frames:  # a finished stage survives a kill and is not redone
        assert status["ingest"] == "cached", status
    for name in SCHEMA_OF:
        assert (out / name).read_bytes() == (ref / name).read_bytes(), name


def test_stale_temporaries_of_a_killed_write_are_removed(tmp_path: Path) -> None:
    """What SIGKILL mid-write leaves (a hidden temporary beside the intact artefact) is
    never read as an artefact and is removed by the next run."""
    from test_robustness_data import tiny_recording

    from pipeline.run.orchestrator import run_pipeline

    rec = tiny_recording(tmp_path / "rec.mcap")
    out = tmp_path / "run"
    run_pipeline(rec, out, until="ingest")
    before = (out / "frames.parquet").read_bytes()
    stale = [out / ".frames.parquet.k1ll3d.tmp", out / ".run.rrd.partial"]
    for s in stale:
        s.write_bytes(before[: len(before) // 2])  # half-written
    res = run_pipeline(rec, out, until="ingest")
    assert [r.status for r in res.stages] == ["cached"]
    assert not any(s.exists() for s in stale)
    assert (out / "frames.parquet").read_bytes() == before


def test_damaged_artefacts_in_the_run_folder_are_redone(tmp_path: Path) -> None:
    """A truncated Parquet artefact or a broken JSON side file is not 'fresh': redone."""
    from test_robustness_data import tiny_recording

    from pipeline.run.orchestrator import run_pipeline

    rec = tiny_recording(tmp_path / "rec.mcap")
    out = tmp_path / "run"
    run_pipeline(rec, out, until="ingest")
    good = {n: (out / n).read_bytes() for n in ("frames.parquet", "recording.json")}
    for name, data in good.items():
        (out / name).write_bytes(data[: len(data) // 3])
        res = run_pipeline(rec, out, until="ingest")
        assert [r.status for r in res.stages] == ["ran"], name
        assert (out / name).read_bytes() == data, name
