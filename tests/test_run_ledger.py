"""The run ledger: a second run with nothing changed answers from run.json alone.

One run of the shipped sample (up to identify) is made once; each test works on
a copy of its run folder (the ledger keys on the recording's bytes, not on
paths, so a copied folder is as good as the original). Every change the ledger
must notice (an artefact byte, the options, ``until``, the recording, a stale
temporary) is checked twice: the ledger misses (``cached_run`` is None), and the
per-stage checks that then decide redo exactly the affected stages.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.run import ledger as run_ledger
from pipeline.run.orchestrator import RunConfig, cached_run, run_pipeline

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
UNTIL = "identify"
STAGES = ["ingest", "touchups", "outliers", "identify", "choose"]
#: what a cached run must not load (the point of the ledger)
HEAVY = ("pandas", "pyarrow", "scipy", "cv2", "numba", "pipeline.stages.ingest.stage")


@pytest.fixture(scope="module")
def first_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(recording, run folder) of one run of the sample up to identify."""
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    d = tmp_path_factory.mktemp("ledger")
    rec = d / "rec.mcap"
    shutil.copyfile(SAMPLE, rec)
    out = d / "run"
    res = run_pipeline(rec, out, until=UNTIL)
    assert [s.status for s in res.stages] == ["ran"] * 5
    return rec, out


@pytest.fixture
def run_copy(first_run: tuple[Path, Path], tmp_path: Path) -> tuple[Path, Path]:
    rec, out = first_run
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    return rec, copy


def _statuses(res) -> list[str]:
    return [s.status for s in res.stages]


def test_run_json_records_fingerprint_and_artefact_hashes(first_run) -> None:
    rec, out = first_run
    led = json.loads((out / "run.json").read_text())["ledger"]
    fp = led["fingerprint"]
    assert fp == run_ledger.fingerprint(rec, RunConfig(), UNTIL)
    assert fp["until"] == UNTIL and fp["config"]["report"] is True
    # every output of every stage that ran, with its content hash; run.json itself not
    want = {"frames.parquet", "detections.parquet", "recording.json", "touchups.parquet"}
    want |= {"inliers.parquet", "parameters.parquet", "residuals.parquet", "targets.parquet"}
    want |= {"calibrated.urdf", "calibration.json", "identify.json", "models.json"}
    want |= {f"calibrated_{m}.urdf" for m in json.loads((out / "models.json").read_text())["order"]}
    assert set(led["artefacts"]) == want
    for name, h in led["artefacts"].items():
        assert h == run_ledger.file_hash(out / name)


def test_unchanged_run_is_answered_by_the_ledger(run_copy) -> None:
    rec, out = run_copy
    hit = cached_run(rec, out, until=UNTIL)
    assert hit is not None
    assert [s.stage for s in hit.stages] == STAGES and _statuses(hit) == ["cached"] * 5
    assert hit.summary == json.loads((out / "identify.json").read_text())
    assert hit.summary["rms_mm"] < 0.1
    # run.json now says what a run with every stage cached says, ledger kept
    run = json.loads((out / "run.json").read_text())
    assert [s["status"] for s in run["stages"]] == ["cached"] * 5
    assert cached_run(rec, out, until=UNTIL) is not None


def test_second_cli_run_in_a_fresh_process_loads_no_numeric_library(run_copy) -> None:
    rec, out = run_copy
    code = (
        "import sys, json\n"
        "from pipeline.cli import main\n"
        f"main(['run', {str(rec)!r}, '--out', {str(out)!r}, '--until', {UNTIL!r}, '-q'])\n"
        f"print(json.dumps({{m: m in sys.modules for m in {list(HEAVY)!r}}}))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    loaded = json.loads(lines[-1])
    assert not any(loaded.values()), loaded
    words = [ln.split() for ln in lines]
    said = [w[:2] for w in words if len(w) > 1 and w[0] in STAGES and w[1] in ("ran", "cached")]
    assert said == [[s, "cached"] for s in STAGES]


def _flip_last_byte(p: Path) -> None:
    data = bytearray(p.read_bytes())
    data[-1] ^= 0xFF
    p.write_bytes(bytes(data))


def test_one_changed_artefact_byte_misses_and_only_its_stage_reruns(run_copy) -> None:
    rec, out = run_copy
    before = (out / "inliers.parquet").read_bytes()
    _flip_last_byte(out / "inliers.parquet")  # Parquet footer broken
    assert cached_run(rec, out, until=UNTIL) is None
    res = run_pipeline(rec, out, until=UNTIL)
    assert _statuses(res) == ["cached", "cached", "ran", "cached", "cached"]
    assert (out / "inliers.parquet").read_bytes() == before  # deterministic: same bytes again
    assert cached_run(rec, out, until=UNTIL) is not None  # ledger written anew


def test_missing_artefact_or_stale_temporary_misses(run_copy) -> None:
    rec, out = run_copy
    (out / "calibrated.urdf").unlink()
    assert cached_run(rec, out, until=UNTIL) is None
    # the choice writes calibrated.urdf again; the fits it is made from stay cached
    assert _statuses(run_pipeline(rec, out, until=UNTIL)) == ["cached"] * 4 + ["ran"]
    assert cached_run(rec, out, until=UNTIL) is not None
    stale = out / ".frames.parquet.abc123.tmp"  # what a kill mid-write leaves
    stale.write_bytes(b"half")
    assert cached_run(rec, out, until=UNTIL) is None
    assert _statuses(run_pipeline(rec, out, until=UNTIL)) == ["cached"] * 5
    assert not stale.exists()


def test_other_options_miss_and_rerun_what_they_change(run_copy) -> None:
    rec, out = run_copy
    offsets = RunConfig(stage_options={"identify": {"model": "offsets"}})
    assert cached_run(rec, out, offsets, until=UNTIL) is None
    res = run_pipeline(rec, out, offsets, until=UNTIL)
    assert _statuses(res) == ["cached", "cached", "cached", "ran", "ran"]
    assert cached_run(rec, out, offsets, until=UNTIL) is not None
    assert cached_run(rec, out, until=UNTIL) is None  # the default options are not this run
    # an option no stage up to identify reads: a ledger miss, every fit cached; the
    # provenance block's run id hashes the request, so calibrated.urdf is restamped
    no_report = RunConfig(report=False, stage_options={"identify": {"model": "offsets"}})
    assert cached_run(rec, out, no_report, until=UNTIL) is None
    assert _statuses(run_pipeline(rec, out, no_report, until=UNTIL)) == ["cached"] * 4 + ["ran"]


def test_other_until_misses_and_the_stages_are_cached(run_copy) -> None:
    rec, out = run_copy
    assert cached_run(rec, out, until="outliers") is None
    res = run_pipeline(rec, out, until="outliers")
    assert [s.stage for s in res.stages] == STAGES[:3] and _statuses(res) == ["cached"] * 3
    hit = cached_run(rec, out, until="outliers")
    assert hit is not None and [s.stage for s in hit.stages] == STAGES[:3]
    assert cached_run(rec, out, until=UNTIL) is None


def test_changed_recording_misses_and_is_ingested_again(run_copy, tmp_path: Path) -> None:
    rec, out = run_copy
    other = tmp_path / "rec.mcap"
    other.write_bytes(rec.read_bytes()[:-1])  # one byte shorter: ends inside the footer
    assert (
        run_ledger.fingerprint(other, RunConfig(), UNTIL)["recording"]
        != (run_ledger.fingerprint(rec, RunConfig(), UNTIL)["recording"])
    )
    assert cached_run(other, out, until=UNTIL) is None
    assert cached_run(rec, out, until=UNTIL) is not None  # the recording, not its path, counts
    res = run_pipeline(other, out, until="ingest")
    assert _statuses(res) == ["ran"]


def test_force_bypasses_the_ledger(run_copy) -> None:
    rec, out = run_copy
    assert _statuses(run_pipeline(rec, out, until="ingest")) == ["cached"]  # via per-stage checks
    assert cached_run(rec, out, until="ingest") is not None
    assert _statuses(run_pipeline(rec, out, until="ingest", force=True)) == ["ran"]


def test_lookup_misses_on_damaged_run_json(run_copy) -> None:
    rec, out = run_copy
    fp = run_ledger.fingerprint(rec, RunConfig(), UNTIL)
    assert run_ledger.lookup(out, fp) is not None
    run = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text("{not json")
    assert run_ledger.lookup(out, fp) is None
    run["ledger"]["artefacts"]["../elsewhere.json"] = "0" * 16
    (out / "run.json").write_text(json.dumps(run))
    assert run_ledger.lookup(out, fp) is None
    (out / "run.json").unlink()
    assert run_ledger.lookup(out, fp) is None
    assert cached_run(rec, out / "nowhere", until=UNTIL) is None
    assert cached_run(rec.with_name("absent.mcap"), out, until=UNTIL) is None


def test_code_digest_covers_the_package_and_schemas(tmp_path: Path, monkeypatch) -> None:
    d = run_ledger.code_digest()
    assert len(d) == 16 and int(d, 16) >= 0
    assert run_ledger.code_digest() == d  # once per process
    # the same digest over a copy, then over the copy with one schema byte changed
    pkg = tmp_path / "pipeline"
    shutil.copytree(run_ledger.PACKAGE_DIR, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(run_ledger.SCHEMA_DIR, tmp_path / "schemas")
    monkeypatch.setattr(run_ledger, "PACKAGE_DIR", pkg)
    monkeypatch.setattr(run_ledger, "SCHEMA_DIR", tmp_path / "schemas")
    run_ledger.code_digest.cache_clear()
    try:
        assert run_ledger.code_digest() == d
        run_ledger.code_digest.cache_clear()
        schema = tmp_path / "schemas" / "frames.json"
        schema.write_text(schema.read_text() + " ")
        assert run_ledger.code_digest() != d
    finally:
        run_ledger.code_digest.cache_clear()
