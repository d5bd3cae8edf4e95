"""vtcal batch: fan-out over an executor, per-recording errors, content caching, resume, Dask.

Recordings: the shipped sample (good_a) and a copy of it (good_b, for the resume
test), plus two corrupt ones (random bytes; a copy cut after 50 kB, before the
robot description). Every batch stops after identify; the shared batch is
good_a among the two corrupt ones.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.batch.run import items_from_paths, load_manifest, open_executor, run_batch
from pipeline.errors import BadInput
from pipeline.io.artefacts import read_artefact, read_meta

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
UNTIL = "identify"
PARQUETS = (
    "frames",
    "detections",
    "touchups",
    "inliers",
    "parameters",
    "residuals",
    "targets",
)
#: the batch of the shared fixture: one good recording among two corrupt ones
BATCH = ("good_a", "junk", "trunc")
#: summary columns that depend on the run (time, process, whether it ran or was cached)
VOLATILE = (
    "seconds",
    "cpu_seconds",
    "peak_rss_mb",
    "worker",
    "run_dir",
    "stages",
    "stages_ran",
    "stages_cached",
)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    d = tmp_path_factory.mktemp("recs")
    good_a = d / "good_a.mcap"
    good_b = d / "good_b.mcap"
    shutil.copyfile(SAMPLE, good_a)
    shutil.copyfile(SAMPLE, good_b)
    junk = d / "junk.mcap"
    junk.write_bytes(os.urandom(4096))
    trunc = d / "trunc.mcap"
    trunc.write_bytes(SAMPLE.read_bytes()[:50_000])
    return {"good_a": good_a, "good_b": good_b, "junk": junk, "trunc": trunc}


@pytest.fixture(scope="module")
def pool_batch(recordings: dict[str, Path], tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("batch_pool")
    items = items_from_paths([recordings[k] for k in BATCH])
    seen: list[tuple[int, int, str]] = []
    result = run_batch(
        items,
        out,
        kind="processes",
        workers=2,
        until=UNTIL,
        progress=lambda done, total, rec: seen.append((done, total, rec.name)),
    )
    return result, seen, pq.read_table(result.summary_path)


def _by_name(result):
    return {o.name: o for o in result.outcomes}


# -- manifests and names ---------------------------------------------------------------


def test_manifest_paths_relative_to_manifest_and_names(tmp_path: Path) -> None:
    sub = tmp_path / "datasets"
    sub.mkdir()
    m = sub / "fleet.toml"
    m.write_text(
        'name = "fleet"\ndescription = "two cells"\n'
        '[[recordings]]\npath = "cells/rec.mcap"\nrobot = "lrmate"\nnotes = "cell 1"\n'
        '[[recordings]]\npath = "other/rec.mcap"\n'
        '[[recordings]]\npath = "/abs/x.mcap"\nname = "cell3"\n'
    )
    man = load_manifest(m)
    assert man.name == "fleet" and man.description == "two cells"
    assert [it.name for it in man.items] == ["rec", "rec-2", "cell3"]
    assert man.items[0].recording == (sub / "cells" / "rec.mcap").absolute()
    assert man.items[0].robot == "lrmate" and man.items[0].notes == "cell 1"
    assert man.items[2].recording == Path("/abs/x.mcap")


@pytest.mark.parametrize(
    "text, words",
    [
        ("[[recordings]]\nname = 'x'\n", "needs a 'path'"),
        ("name = 'empty'\n", "no [[recordings]]"),
        ("[[recordings]\npath = 'a'\n", "not a readable TOML"),
        ("[[recordings]]\npath = 'a.mcap'\nrobt = 'x'\n", "unknown key(s) robt"),
        ("[[recordings]]\npath='a'\nname='x'\n[[recordings]]\npath='b'\nname='x'\n", "repeated"),
        ("[[recordings]]\npath = 'a.mcap'\nname = '../up'\n", "not a plain folder name"),
    ],
)
def test_bad_manifest_is_one_line_bad_input(tmp_path: Path, text: str, words: str) -> None:
    m = tmp_path / "m.toml"
    m.write_text(text)
    with pytest.raises(BadInput) as err:
        load_manifest(m)
    msg = str(err.value)
    assert "\n" not in msg and str(m) in msg and words in msg


@pytest.mark.parametrize("manifest", sorted((REPO / "datasets").glob("*.toml")), ids=str)
def test_shipped_manifests_parse(manifest: Path) -> None:
    man = load_manifest(manifest)
    assert man.items and len({it.name for it in man.items}) == len(man.items)
    for it in man.items:
        assert it.recording.is_absolute() and it.robot and it.notes
        assert it.recording.suffix == ".mcap"
    shipped = [it for it in man.items if it.name == "sample_lrmate"]
    assert not shipped or shipped[0].recording.samefile(SAMPLE)


def test_repeated_stems_get_distinct_run_folders() -> None:
    items = items_from_paths(["a/rec.mcap", "b/rec.mcap", "rec-2.mcap", "c/rec.mcap"])
    names = [it.name for it in items]
    assert len(set(names)) == 4 and names[0] == "rec" and names[2] == "rec-2"


def test_bad_executor_options_are_bad_input() -> None:
    with pytest.raises(BadInput, match="--scheduler"), open_executor("processes", 1, "tcp://x:1"):
        pass
    with pytest.raises(BadInput, match="--executor"), open_executor("threads"):
        pass
    with pytest.raises(BadInput, match="--workers"), open_executor("processes", 0):
        pass


# -- a batch with corrupt recordings among good ones ----------------------------------


def test_corrupt_recordings_reported_good_ones_finish(pool_batch) -> None:
    result, seen, _ = pool_batch
    by = _by_name(result)
    assert [o.name for o in result.outcomes] == list(BATCH)
    for name in ("good_a",):
        o = by[name]
        assert o.status == "ok", o.error
        assert [s for s, _, _ in o.stages] == [
            "ingest",
            "touchups",
            "outliers",
            "identify",
            "choose",
        ]
        assert all(st == "ran" for _, st, _ in o.stages)
        assert (Path(o.run_dir) / "identify.json").exists()
        assert o.figures["rms_mm"] is not None and o.figures["rms_mm"] < 0.1
        assert o.robot_urdf  # read from the recording's URDF
    for name in ("junk", "trunc"):
        o = by[name]
        assert o.status == "error" and o.error_kind == "bad_input" and o.exit_code == 2
        assert "\n" not in o.error and f"{name}.mcap" in o.error
    assert "not an MCAP file" in by["junk"].error
    # the cross-run table of the identified runs (vtcal compare) beside the summary
    assert result.compare is not None, result.compare_note
    assert set(result.compare.runs["run"]) == {"good_a"}
    assert (result.out_dir / "compare.parquet").exists()
    assert (result.out_dir / "compare.html").exists()
    # progress saw every recording once, counting up to the total
    assert sorted(n for _, _, n in seen) == sorted(by)
    assert [d for d, _, _ in seen] == [1, 2, 3] and {t for _, t, _ in seen} == {3}


def test_summary_parquet_follows_its_schema(pool_batch) -> None:
    result, _, _ = pool_batch
    df = read_artefact(result.summary_path, "batch_summary")
    assert list(df["name"]) == list(BATCH)
    assert list(df["status"]) == ["ok", "error", "error"]
    assert list(df["exit_code"]) == [0, 2, 2]
    ok = df[df["status"] == "ok"]
    assert (ok["stages_ran"] == 5).all() and (ok["model"] == ok["model"].iloc[0]).all()
    assert ok["n_used"].notna().all() and ok["rms_mm"].notna().all()
    bad = df[df["status"] != "ok"]
    assert bad["model"].isna().all() and (bad["error"].str.len() > 0).all()
    # memory per worker is measured and bounded
    assert df["peak_rss_mb"].notna().all() and (df["peak_rss_mb"] < 2000).all()
    assert read_meta(result.summary_path)["stage"] == "batch"


def test_second_batch_is_cached_and_force_reruns(pool_batch, recordings) -> None:
    result, _, _ = pool_batch
    files = {
        o.name: {p.name: p.read_bytes() for p in Path(o.run_dir).glob("*.parquet")}
        for o in result.outcomes
        if o.status == "ok"
    }
    items = items_from_paths([recordings[k] for k in BATCH])
    again = run_batch(items, result.out_dir, kind="processes", workers=2, until=UNTIL)
    by = _by_name(again)
    for name in ("good_a",):
        assert [st for _, st, _ in by[name].stages] == ["cached"] * 5
        now = {p.name: p.read_bytes() for p in Path(by[name].run_dir).glob("*.parquet")}
        assert now == files[name]
    assert by["junk"].status == "error" and by["trunc"].status == "error"
    forced = run_batch(items[:1], result.out_dir, workers=1, until=UNTIL, force=True)
    assert [st for _, st, _ in forced.outcomes[0].stages] == ["ran"] * 5


def test_interrupted_batch_resumes_where_it_stopped(
    recordings: dict[str, Path], tmp_path: Path
) -> None:
    """Ctrl-C (SIGINT to the process group) after the first recording; the rerun caches it."""
    out = tmp_path / "batch"
    recs = [str(recordings["good_a"]), str(recordings["good_b"])]
    cmd = [sys.executable, "-m", "pipeline", "batch", *recs, "--out", str(out)]
    cmd += ["--until", UNTIL, "--workers", "1"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"}
    proc = subprocess.Popen(
        cmd,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:  # the per-recording line comes when its outcome is back
        lines.append(line)
        if line.strip().startswith("ok") and "good_a" in line:
            break
    else:
        pytest.fail(f"good_a never reported: {''.join(lines)} {proc.communicate()}")
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    summary = read_artefact(out / "summary.parquet", "batch_summary")
    status = dict(zip(summary["name"], summary["status"], strict=True))
    assert status["good_a"] == "ok"
    if status["good_b"] != "ok":  # the usual case: interrupted inside good_b
        assert proc.returncode == 130 and "interrupted; what finished" in err
        assert status["good_b"] in ("not_run", "error")
    resumed = run_batch(items_from_paths(recs), out, workers=1, until=UNTIL)
    by = _by_name(resumed)
    assert [st for _, st, _ in by["good_a"].stages] == ["cached"] * 5
    assert by["good_b"].status == "ok"


def _pool_workers() -> list[int]:
    """Pids of this process's grandchildren under a multiprocessing fork server."""
    me = os.getpid()
    parent: dict[int, int] = {}
    cmd: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd[int(d.name)] = (d / "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        parent[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    servers = {p for p, pp in parent.items() if pp == me and "forkserver" in cmd.get(p, "")}
    return [p for p, pp in parent.items() if pp in servers]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_worker_killed_mid_task_is_retried_alone(recordings, tmp_path: Path) -> None:
    """SIGKILL (as the OOM killer would) the worker while it ingests: the pool
    breaks, the recording is run again in a fresh pool and finishes."""
    import threading

    items = items_from_paths([recordings["good_a"]])
    done: dict[str, object] = {}

    def go() -> None:
        done["result"] = run_batch(items, tmp_path, workers=1, until="ingest", compare=False)

    before = set(_pool_workers())
    th = threading.Thread(target=go)
    th.start()
    killed = None
    while th.is_alive() and killed is None:
        new = [p for p in _pool_workers() if p not in before]
        if new:
            killed = new[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.01)
    th.join(timeout=120)
    assert killed is not None, "never saw the worker"
    res = done["result"]
    o = res.outcomes[0]  # type: ignore[attr-defined]
    assert o.status == "ok" and o.retried, o.error
    assert o.worker.split(":")[1] != str(killed)
    assert read_artefact(res.summary_path, "batch_summary")["retried"].tolist() == [True]  # type: ignore[attr-defined]


def test_workers_run_single_threaded_numerics() -> None:
    """Workers come from a fork server started with OMP_NUM_THREADS=1 and friends
    (set before numpy loads there); this process's environment is left as it was."""
    from pipeline.batch.run import THREAD_ENV

    before = {k: os.environ.get(k) for k in THREAD_ENV}
    with open_executor("processes", 1) as pool:
        got = {k: pool.submit(os.getenv, k).result() for k in THREAD_ENV}
        probe = "'pipeline.run.orchestrator' in __import__('sys').modules"
        preloaded = pool.submit(eval, probe).result()
    assert got == THREAD_ENV
    assert preloaded  # the pipeline is imported once in the fork server, not per worker
    assert {k: os.environ.get(k) for k in THREAD_ENV} == before


def test_workers_are_recycled_after_n_recordings(recordings, tmp_path: Path) -> None:
    """--recycle bounds a worker's lifetime: a fresh process after N recordings."""
    items = items_from_paths([recordings["junk"], recordings["trunc"], recordings["junk"]])
    once = run_batch(items, tmp_path / "a", workers=1, until="ingest", recycle_after=1)
    assert len({o.worker for o in once.outcomes}) == 3
    never = run_batch(items, tmp_path / "b", workers=1, until="ingest", recycle_after=0)
    assert len({o.worker for o in never.outcomes}) == 1
    assert [o.error_kind for o in never.outcomes] == ["bad_input"] * 3
    with pytest.raises(BadInput, match="--recycle"):
        run_batch(items, tmp_path / "c", recycle_after=-1)


# -- the CLI -------------------------------------------------------------------------------


def test_cli_batch_from_manifest(pool_batch, recordings, capsys) -> None:
    """Same run folders as the fixture (names from the manifest): everything cached."""
    from pipeline.cli import main

    result, _, _ = pool_batch
    m = recordings["good_a"].parent / "m.toml"
    m.write_text(
        '[[recordings]]\npath = "good_a.mcap"\nrobot = "lrmate"\nnotes = "first"\n'
        '[[recordings]]\npath = "junk.mcap"\n'
    )
    with pytest.raises(SystemExit) as ex:
        main(["batch", "--manifest", str(m), "--out", str(result.out_dir), "--until", UNTIL])
    assert ex.value.code == 1  # one recording failed
    out, err = capsys.readouterr()
    assert "good_a" in out and "junk" in out and "1 of 2 recording(s) ok" in out
    assert "1 of 2 recording(s) failed" in err
    df = read_artefact(result.summary_path, "batch_summary")
    assert list(df["name"]) == ["good_a", "junk"]
    assert df["robot"].iloc[0] == "lrmate" and df["notes"].iloc[0] == "first"
    assert df["stages_cached"].iloc[0] == 5


def test_cli_batch_needs_recordings(capsys) -> None:
    from pipeline.cli import main

    with pytest.raises(SystemExit) as ex:
        main(["batch", "--out", "/tmp/never"])
    assert ex.value.code == 2
    assert "no recordings" in capsys.readouterr().err


# -- Dask ----------------------------------------------------------------------------------


def test_dask_gives_the_same_artefacts(pool_batch, recordings, tmp_path: Path) -> None:
    """The fixture's batch again under ``kind="dask"``: a LocalCluster of two
    single-threaded worker processes on loopback, no dashboard."""
    pytest.importorskip("distributed")
    result, _, pool_summary = pool_batch
    items = items_from_paths([recordings[k] for k in BATCH])
    dres = run_batch(items, tmp_path, kind="dask", workers=2, until=UNTIL)
    assert [o.status for o in dres.outcomes] == [o.status for o in result.outcomes]
    assert [o.error for o in dres.outcomes] == [o.error for o in result.outcomes]
    pool_pids = {o.worker for o in result.outcomes}
    assert all(o.worker and o.worker not in pool_pids for o in dres.outcomes)
    n = 0
    for o in dres.outcomes:
        if o.status != "ok":
            continue
        for name in PARQUETS:
            a = pq.read_table(Path(result.out_dir) / o.name / f"{name}.parquet")
            b = pq.read_table(Path(o.run_dir) / f"{name}.parquet")
            assert a.equals(b, check_metadata=True), f"{o.name}/{name}.parquet differs"
            n += 1
    assert n == len(PARQUETS)
    sa = pool_summary.drop(list(VOLATILE))
    sb = pq.read_table(dres.summary_path).drop(list(VOLATILE))
    assert sa.equals(sb)


# -- the run ledger: a batch with nothing changed --------------------------------------


def _ledger_batch(pool_batch, tmp_path: Path):
    """Two copies of the sample (good_a, good_b) and a batch folder whose two run
    folders are copies of the fixture's good_a run: both complete, as the ledger sees it."""
    result, _, _ = pool_batch
    recs = tmp_path / "recs"
    recs.mkdir()
    for name in ("good_a", "good_b"):
        shutil.copyfile(SAMPLE, recs / f"{name}.mcap")
        shutil.copytree(Path(result.out_dir) / "good_a", tmp_path / "batch" / name)
    return items_from_paths([recs / "good_a.mcap", recs / "good_b.mcap"]), tmp_path / "batch"


def _refuse_pool(monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.batch.run as batch

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a worker pool was started")

    monkeypatch.setattr(batch, "process_context", refuse)
    monkeypatch.setattr(batch, "prestart", refuse)


COMPARE_FILES = ("summary.parquet", "compare.parquet", "compare.html")


def test_fully_cached_batch_starts_no_pool_and_keeps_its_files(
    pool_batch, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    items, out = _ledger_batch(pool_batch, tmp_path)
    with monkeypatch.context() as m:
        _refuse_pool(m)
        first = run_batch(items, out, workers=2, until=UNTIL)
        assert [o.status for o in first.outcomes] == ["ok", "ok"]
        for o in first.outcomes:  # answered in this process, from the ledger
            assert o.worker.endswith(f":{os.getpid()}")
            assert [st for _, st, _ in o.stages] == ["cached"] * 5
            assert o.figures["rms_mm"] is not None and o.figures["rms_mm"] < 0.1
        assert not first.reused and (out / "batch.json").exists()  # summary written once
        assert any("good_b" in line for line in first.compare_lines)
        files = {n: (out / n).read_bytes() for n in COMPARE_FILES}
        again = run_batch(items, out, workers=2, until=UNTIL)
    assert again.reused
    assert {n: (out / n).read_bytes() for n in COMPARE_FILES} == files
    assert again.compare_lines == first.compare_lines
    assert again.compare_note == first.compare_note
    assert list(again.summary["name"]) == ["good_a", "good_b"]  # read from the file
    assert again.compare is not None and set(again.compare.runs["run"]) == {"good_a", "good_b"}
    # other options are another batch: the files are written again (runs still cached)
    with monkeypatch.context() as m:
        _refuse_pool(m)
        other = run_batch(items, out, workers=2, until=UNTIL, compare=False)
    assert not other.reused and (out / "summary.parquet").read_bytes() != files["summary.parquet"]


def test_fully_cached_cli_batch_loads_no_numeric_library(pool_batch, tmp_path: Path) -> None:
    """A cold `vtcal batch` with nothing changed: no pandas, no fork server, same output."""
    items, out = _ledger_batch(pool_batch, tmp_path)
    first = run_batch(items, out, workers=2, until=UNTIL)
    summary = (out / "summary.parquet").read_bytes()
    argv = ["batch", *(str(it.recording) for it in items), "--out", str(out), "--until", UNTIL]
    code = (
        "import json, os, sys\n"
        "from pipeline.cli import main\n"
        f"main({argv!r})\n"
        "kids = []\n"
        "for d in filter(str.isdigit, os.listdir('/proc')):\n"
        "    try:\n"
        "        stat = open(f'/proc/{d}/stat').read()\n"
        "    except OSError:\n"
        "        continue\n"
        "    if stat.rsplit(')', 1)[1].split()[1] == str(os.getpid()):\n"
        "        kids.append(d)\n"
        "heavy = ['pandas', 'pyarrow', 'scipy', 'cv2', 'numba', 'pipeline.stages.ingest.stage']\n"
        "print(json.dumps({'kids': kids, 'loaded': [m for m in heavy if m in sys.modules]}))\n"
    )
    env = {**os.environ, "COLUMNS": "200"}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.rstrip().splitlines()
    got = json.loads(lines[-1])
    assert got == {"kids": [], "loaded": []}
    assert (out / "summary.parquet").read_bytes() == summary
    for line in first.compare_lines:  # the comparison, printed from batch.json
        assert line.rstrip() in lines
    assert "2 of 2 recording(s) ok" in proc.stdout


def test_batch_with_one_changed_recording_rebuilds_the_summary(
    pool_batch, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    items, out = _ledger_batch(pool_batch, tmp_path)
    with monkeypatch.context() as m:
        _refuse_pool(m)
        run_batch(items, out, workers=2, until=UNTIL)
    before = (out / "summary.parquet").read_bytes()
    Path(items[1].recording).write_bytes(os.urandom(4096))  # good_b replaced: not an MCAP now
    res = run_batch(items, out, workers=2, until=UNTIL)
    assert not res.reused
    a, b = res.outcomes
    assert a.status == "ok" and [st for _, st, _ in a.stages] == ["cached"] * 5
    assert a.worker.endswith(f":{os.getpid()}")
    assert b.status == "error" and b.error_kind == "bad_input"
    assert not b.worker.endswith(f":{os.getpid()}")  # sent to a worker
    assert (out / "summary.parquet").read_bytes() != before
    df = read_artefact(out / "summary.parquet", "batch_summary")
    assert list(df["status"]) == ["ok", "error"]
    assert not (out / "batch.json").exists()  # a batch with a failure is never taken as unchanged


def test_abort_after_ctrl_c_does_not_wait_for_a_stuck_worker() -> None:
    """A worker that never hands its task back (stuck after Ctrl-C) is terminated after
    the grace period instead of hanging the batch in shutdown(wait=True)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.batch.run import _Slot

    ctx = mp.get_context("spawn")
    slot = _Slot(None, 1, lambda: ProcessPoolExecutor(max_workers=1, mp_context=ctx), 0)
    assert slot.make is not None
    slot.executor = slot.make()
    slot.executor.submit(time.sleep, 120)  # never hands its task back in time
    procs = []
    t_wait = time.monotonic()
    while not procs and time.monotonic() - t_wait < 30:
        procs = list(slot.executor._processes.values())
        time.sleep(0.05)
    assert procs, "the pool never started its worker"
    t0 = time.monotonic()
    slot.abort(grace_s=0.5)
    assert time.monotonic() - t0 < 10
    assert slot.executor is None
    assert not any(p.is_alive() for p in procs)


def test_the_batch_table_is_not_clipped_off_a_terminal(pool_batch) -> None:
    """Printed to a file or pipe, every row of the table is whole (rich clips to 80 columns)."""
    import io

    from pipeline.commands.batch import print_summary, summary_console

    result = pool_batch[0] if isinstance(pool_batch, tuple) else pool_batch
    buf = io.StringIO()
    print_summary(summary_console(buf), result)
    text = buf.getvalue()
    assert "…" not in text, text
    for o in result.outcomes:
        row = next(line for line in text.splitlines() if o.name in line)
        assert o.status in row, row  # the name and its status on one line, not wrapped
    assert max(len(line) for line in text.splitlines()) > 80
