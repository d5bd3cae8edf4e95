"""The report built by the warm process (pipeline.report.warm) is the report built here.

``vtcal run`` forks a process after ingest that loads the Rerun SDK and reads the
touch-ups' frames while the solver stages run, then builds report.html and run.rrd.
These tests hold it to the in-process build byte for byte, check that an error
there is the run's error, that a dead process only means building here, and that
it is not started where it must not run.
"""

from __future__ import annotations

import shutil
from functools import partial
from pathlib import Path

import pandas as pd
import pytest

from pipeline.errors import BadInput
from pipeline.report import outputs, warm
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.stages import parallel_map

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"


@pytest.fixture
def cores_free(monkeypatch):
    """Two free cores whatever the machine's load (the start condition under test)."""
    monkeypatch.setattr(parallel_map, "free_workers", lambda limit=2, **k: 2)


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory) -> Path:
    """The shipped sample run end to end, the report by the warm process (counted)."""
    out = tmp_path_factory.mktemp("warm") / "run"
    used = []
    mp = pytest.MonkeyPatch()
    mp.setattr(parallel_map, "free_workers", lambda limit=2, **k: 2)
    build = warm.WarmReport.build

    def counting(self, run_dir, tolerance_mm):
        got = build(self, run_dir, tolerance_mm)
        used.append(got is not None)
        return got

    mp.setattr(warm.WarmReport, "build", counting)
    prefetch = warm.WarmReport.prefetch
    read_after = []

    def reading(self, run_dir):
        read_after.append((run_dir / "touchups.parquet").exists())
        return prefetch(self, run_dir)

    mp.setattr(warm.WarmReport, "prefetch", reading)
    try:
        run_pipeline(SAMPLE, out, RunConfig(), force=True)
    finally:
        mp.undo()
    assert used == [True]  # the run's report came from the warm process
    assert read_after == [True]  # told to read its frames once, after the touch-ups stage
    return out


def test_the_warm_report_is_the_in_process_report(sample_run, tmp_path, cores_free) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(sample_run, a)
    shutil.copytree(sample_run, b)
    w = warm.WarmReport.start()
    assert w is not None
    w.prefetch(a)
    got = w.build(a, None)
    assert got == (a / "report.html", a / "run.rrd")
    outputs.build_outputs(b, None)
    assert (a / "report.html").read_bytes() == (b / "report.html").read_bytes()
    assert _rrd_content(a / "run.rrd") == _rrd_content(b / "run.rrd")
    # the run's own recording was built the same way (its page shows the run's timings)
    assert _rrd_content(sample_run / "run.rrd") == _rrd_content(b / "run.rrd")


def _rrd_content(path: Path) -> list[str]:
    """What run.rrd holds, chunk by chunk, without the row ids (they carry a clock)."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if "RowId" not in n}
        rows.append(repr((chunk.entity_path, sorted(cols.items()))))
    assert len(rows) > 10
    return sorted(rows)


def test_an_error_in_the_warm_process_is_raised_here(sample_run, tmp_path, monkeypatch, cores_free):
    def broken(run_dir, tolerance_mm=None, **_):
        raise BadInput(f"{run_dir}: something the report could not read")

    monkeypatch.setattr(outputs, "build_outputs", broken)  # before the fork: inherited
    w = warm.WarmReport.start()
    assert w is not None
    with pytest.raises(BadInput, match="something the report could not read"):
        w.build(tmp_path, None)


def test_a_dead_warm_process_means_building_here(tmp_path, cores_free) -> None:
    w = warm.WarmReport.start()
    assert w is not None
    w._process.kill()
    w._process.join()
    assert w.build(tmp_path, None) is None
    w.close()  # idempotent


def test_not_started_without_a_free_core_or_in_a_worker(monkeypatch) -> None:
    monkeypatch.setattr(parallel_map, "free_workers", lambda limit=2, **k: 1)
    assert warm.WarmReport.start() is None
    monkeypatch.setattr(parallel_map, "free_workers", lambda limit=2, **k: 2)
    monkeypatch.setenv("VTCAL_WARM_REPORT", "0")
    assert warm.WarmReport.start() is None
    monkeypatch.delenv("VTCAL_WARM_REPORT")
    monkeypatch.setattr(parallel_map, "free_workers", lambda limit=2, **k: 2)
    monkeypatch.setattr(warm.multiprocessing, "parent_process", lambda: object())
    assert warm.WarmReport.start() is None


def test_the_warm_process_computes_the_reports_code_digest_as_here(monkeypatch, cores_free):
    """The report's cache key takes its code digest from the warm process (a fork of this
    one): the same as here, a function replaced before the run included."""
    from pipeline.report import html
    from pipeline.run import code_key

    digest = partial(code_key.stage_code_digest, "report")  # what the orchestrator hands in
    w = warm.WarmReport.start(digest)
    assert w is not None
    assert w.code_digest() == code_key.stage_code_digest("report")
    w.close()
    assert w.code_digest() is None  # closed: the caller computes it

    def other_build_report(*args, **kwargs):  # a plug-in's page
        return None

    monkeypatch.setattr(html, "build_report", other_build_report)
    changed = code_key.stage_code_digest("report")
    w = warm.WarmReport.start(digest)
    assert w is not None
    assert w.code_digest() == changed
    w.close()
    w = warm.WarmReport.start()  # handed no digest function: the caller computes it
    assert w is not None
    assert w.code_digest() is None
    w.close()


def test_the_reports_views_made_once_per_load_are_the_direct_ones(sample_run) -> None:
    """touchup_table, touchup_frames and detection_ellipse are made once per load
    (``RunData.derived``): the same values as made directly, handed out as copies."""
    import numpy as np

    from pipeline.report.data import load_run
    from pipeline.report.touchup_views import detection_ellipse, touchup_frames

    data = load_run(sample_run)
    first = data.touchup_table()
    assert first is not None and len(first)
    first["reason"] = "changed by a caller"
    again = data.touchup_table()
    assert again is not None and not (again["reason"] == "changed by a caller").any()
    pd.testing.assert_frame_equal(again, load_run(sample_run)._touchup_table())
    frames = touchup_frames(data)
    frames[next(iter(frames))].append(-1)
    assert -1 not in sum(touchup_frames(data).values(), [])
    det = data.detections
    assert det is not None
    for f in sorted(set(det["frame_index"].tolist())):
        rows = det[det["frame_index"] == f]
        r = rows.iloc[0]
        want = None
        if np.isfinite(r["u"]):
            want = (r["u"], r["v"], r["s"], r["s_minor"], r["angle"])
        assert detection_ellipse(data, f) == want, f
    assert detection_ellipse(data, int(det["frame_index"].max()) + 1) is None


def test_the_warm_process_is_a_busy_core_while_it_reads_frames(sample_run, cores_free) -> None:
    """From :meth:`WarmReport.prefetch` until the process says it has read the frames,
    the fits started meanwhile count its core as busy; the messages after it are still
    answered in order."""
    import time

    from pipeline.run import code_key

    w = warm.WarmReport.start(partial(code_key.stage_code_digest, "report"))
    assert w is not None
    try:
        assert w.cores_busy() == 0
        assert w.cores_busy in parallel_map._BUSY
        w.prefetch(sample_run)
        assert w.cores_busy() == 1  # it imports the SDK before it reads: not done yet
        deadline = time.monotonic() + 60
        while w.cores_busy() and time.monotonic() < deadline:
            time.sleep(0.02)
        assert w.cores_busy() == 0
        assert w.code_digest() == code_key.stage_code_digest("report")
    finally:
        w.close()
    assert w.cores_busy not in parallel_map._BUSY
