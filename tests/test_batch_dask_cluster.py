"""vtcal batch on a Dask cluster started apart from vtcal: scheduler and workers as processes.

A ``dask scheduler`` and two ``dask worker --nthreads 1`` processes are started
on 127.0.0.1 (ports chosen by the OS, found through the scheduler file), with
``PYTHONPATH`` naming this checkout so the workers import the ``pipeline``
under test, and a working directory of their own (so a relative ``--out``
resolved against theirs would land elsewhere). The batch is the shipped sample
and a copy, up to identify: its Parquet artefacts must be byte-identical to
the process pool's. The module fixture's finalizer stops every process group
it started, whether the tests pass or not.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("distributed")

from pipeline.batch.cluster import PROBE_PREFIX, preflight, worker_facts  # noqa: E402
from pipeline.batch.run import items_from_paths, run_batch  # noqa: E402
from pipeline.cli import main  # noqa: E402
from pipeline.errors import BadInput  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
UNTIL = "identify"
START_S = 60.0


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def _start(args: list[str], cwd: Path, log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "dask", *args],
            cwd=cwd,
            env=_env(),
            stdout=f,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: the nanny's worker goes with it
        )


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGTERM, 15.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def _scheduler(tmp: Path, name: str, procs: list[subprocess.Popen[bytes]]) -> tuple[str, Path]:
    """Start a scheduler on 127.0.0.1 at a port the OS picks; its address from its file."""
    sfile = tmp / f"{name}.json"
    proc = _start(
        ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
         "--scheduler-file", str(sfile)],
        tmp, tmp / f"{name}.log",
    )  # fmt: skip
    procs.append(proc)
    t0 = time.monotonic()
    while not sfile.exists() or not sfile.read_text().strip():
        if proc.poll() is not None or time.monotonic() - t0 > START_S:
            pytest.fail(f"dask scheduler did not start: {(tmp / f'{name}.log').read_text()}")
        time.sleep(0.2)
    time.sleep(0.2)  # the file is written whole, but be sure it is closed
    return str(json.loads(sfile.read_text())["address"]), sfile


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Address of a scheduler with two single-threaded workers, all separate processes."""
    from distributed import Client

    tmp = tmp_path_factory.mktemp("cluster")
    wdir = tmp / "workers_cwd"
    wdir.mkdir()
    procs: list[subprocess.Popen[bytes]] = []
    try:
        address, sfile = _scheduler(tmp, "scheduler", procs)
        for k in range(2):
            procs.append(
                _start(
                    [
                        "worker",
                        "--scheduler-file",
                        str(sfile),
                        "--nthreads",
                        "1",
                        "--host",
                        "127.0.0.1",
                        "--no-dashboard",
                        "--name",
                        f"w{k}",
                        "--local-directory",
                        str(tmp / f"w{k}"),
                    ],
                    wdir,
                    tmp / f"worker{k}.log",
                )  # fmt: skip
            )
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=START_S)
        yield address
    finally:
        for proc in reversed(procs):  # workers first, then the scheduler
            _stop(proc)


def _worker_pids(address: str) -> set[int]:
    from distributed import Client

    with Client(address, timeout="30s") as client:
        return set(client.run(os.getpid).values())


def _parquets(run_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(run_dir.glob("*.parquet"))}


def test_cluster_batch_gives_the_process_pools_artefacts(
    cluster: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not SAMPLE.exists():
        pytest.skip(f"shipped sample missing: {SAMPLE}")
    recs = tmp_path / "recs"
    recs.mkdir()
    paths = [recs / "cell_a.mcap", recs / "cell_b.mcap"]
    for p in paths:
        shutil.copyfile(SAMPLE, p)

    pool = run_batch(items_from_paths(paths), tmp_path / "pool", kind="processes", workers=2,
                     until=UNTIL, compare=False)  # fmt: skip
    assert [o.status for o in pool.outcomes] == ["ok", "ok"], [o.error for o in pool.outcomes]

    client_cwd = tmp_path / "client"
    client_cwd.mkdir()
    monkeypatch.chdir(client_cwd)
    args = ["batch", *map(str, paths), "--out", "fleet", "--executor", "dask"]
    main([*args, "--scheduler", cluster, "--until", UNTIL, "-q"])  # exits only on failure

    out = client_cwd / "fleet"  # the relative --out is the batch process's, not the workers'
    pids = _worker_pids(cluster)
    import pyarrow.parquet as pq

    summary = pq.read_table(out / "summary.parquet").to_pydict()
    assert summary["status"] == ["ok", "ok"]
    ran_on = {int(w.rsplit(":", 1)[1]) for w in summary["worker"]}
    assert ran_on <= pids and os.getpid() not in ran_on
    for name in ("cell_a", "cell_b"):
        a, b = _parquets(tmp_path / "pool" / name), _parquets(out / name)
        assert len(a) == 7 and a.keys() == b.keys()
        for f in a:
            assert a[f] == b[f], f"{name}/{f} differs between the process pool and the cluster"
    assert not list(out.glob(f"{PROBE_PREFIX}*"))


@pytest.fixture(scope="module")
def lonely(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Address of a scheduler that no worker ever joins."""
    tmp = tmp_path_factory.mktemp("lonely")
    procs: list[subprocess.Popen[bytes]] = []
    try:
        yield _scheduler(tmp, "lonely", procs)[0]
    finally:
        for proc in procs:
            _stop(proc)


def test_preflight_on_the_cluster(cluster: str, lonely: str, tmp_path: Path) -> None:
    """Two workers found and checked, the probe file removed; a folder without the
    probe is reported unseen; a scheduler without workers is bad input."""
    from distributed import Client

    with Client(cluster, timeout="30s") as client:
        assert preflight(client, cluster, tmp_path, wait_s=10) == 2
    assert not list(tmp_path.iterdir())
    facts = worker_facts(str(tmp_path), f"{PROBE_PREFIX}none", "x")
    assert facts["sees_out"] is False and facts["pid"] == os.getpid()
    with Client(lonely, timeout="30s") as client:
        with pytest.raises(BadInput, match="no worker connected within 1 s"):
            preflight(client, lonely, tmp_path, wait_s=1)


def test_cli_scheduler_without_workers_is_bad_input(
    lonely: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    """One stderr line naming the scheduler, exit 2, nothing written in the batch folder."""
    import pipeline.batch.cluster

    monkeypatch.setattr(pipeline.batch.cluster, "WORKER_WAIT_S", 1.0)
    out = tmp_path / "fleet"
    with pytest.raises(SystemExit) as ex:
        main(["batch", str(SAMPLE), "--out", str(out), "--executor", "dask",
              "--scheduler", lonely, "-q"])  # fmt: skip
    assert ex.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"vtcal: error: --scheduler {lonely}: no worker connected within 1 s"]
    assert not list(out.iterdir())
