"""Where a batch's tasks run: one-process worker pools (single-threaded numerics) or Dask."""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from concurrent.futures import Executor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import BadInput

if TYPE_CHECKING:
    pass


#: Executors ``vtcal batch --executor`` accepts.
EXECUTORS = ("processes", "dask")


#: Environment that keeps numeric libraries to one thread in a worker process.
THREAD_ENV: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


#: Modules the process pool's fork server imports once, so that workers start warm
#: (what ``run_pipeline`` imports even when every stage is cached; the report's
#: rendering libraries load in a worker only when it renders a report).
PRELOAD = (
    "pipeline.batch.run",
    "pipeline.run.orchestrator",
    "pipeline.stages.ingest.stage",
    "pipeline.stages.detect.detector",
    "pipeline.stages.touchups.stage",
    "pipeline.stages.outliers.stage",
    "pipeline.stages.identify.stage",
    "pipeline.stages.crossval.stage",
    "pipeline.stages.choose.stage",
    "pipeline.stages.ingest.node",
    "pipeline.stages.touchups.node",
    "pipeline.stages.outliers.node",
    "pipeline.stages.identify.node",
    "pipeline.stages.crossval.node",
    "pipeline.stages.choose.node",
)

#: what a batch's workers load besides before their first recording: the lazily loaded
#: modules and the detector's compiled code (a new worker's first recording otherwise
#: pays them, ~1.6 CPU s: pipeline/batch/warm.py). The batch passes it as ``preload``;
#: the audit, whose workers neither detect nor report, does not.
RUN_PRELOAD = ("pipeline.batch.warm",)


@contextlib.contextmanager
def _env(values: dict[str, str]) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def process_context(preload: tuple[str, ...] = ()) -> Any:
    """Multiprocessing context for the pool: a fork server, warm and single-threaded.

    The fork server is a fresh interpreter started with :data:`THREAD_ENV` in its
    environment; it imports the pipeline once (:data:`PRELOAD`) and forks every
    worker from itself, so workers start in milliseconds, share the imported code
    pages, and are never forked from a multi-threaded parent. Falls back to
    ``spawn`` where there is no fork server. ``preload``: modules it imports besides
    (``vtcal audit``'s, :mod:`pipeline.audit.engine`), when it is not running yet.
    """
    import multiprocessing as mp

    try:
        ctx = mp.get_context("forkserver")
    except ValueError:  # pragma: no cover - Windows
        return mp.get_context("spawn")
    from multiprocessing import forkserver

    ctx.set_forkserver_preload([*PRELOAD, *preload])
    with _env(THREAD_ENV):
        forkserver.ensure_running()
    return ctx


def prestart(kind: str = "processes", preload: tuple[str, ...] = ()) -> None:
    """Start the process pool's fork server now, so it imports the pipeline while
    this process gets on with its own imports (``vtcal batch`` calls it first)."""
    if kind == "processes":
        with contextlib.suppress(Exception):
            process_context(preload)


def default_workers() -> int:
    """Cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def open_executor(
    kind: str = "processes",
    workers: int | None = None,
    scheduler: str | None = None,
    out_dir: Path | None = None,
    preload: tuple[str, ...] = (),
) -> Iterator[Executor]:
    """An :class:`~concurrent.futures.Executor` for a batch, shut down on exit.

    :func:`run_batch` uses it for Dask; for ``"processes"`` it builds its own
    one-process pools (see there) and this gives a plain pool of ``workers``
    processes for callers who pass their own ``executor``.

    Parameters
    ----------
    kind : ``"processes"`` (local process pool) or ``"dask"`` (Dask distributed)
    workers : worker processes (default: the usable cores); with Dask and a
        ``scheduler`` the cluster's own workers are used and this is ignored
    scheduler : Dask scheduler address (``tcp://host:8786``); without it a
        ``LocalCluster`` of ``workers`` single-threaded processes is started on loopback
    out_dir : the batch folder; with a ``scheduler``, the cluster's workers are
        first checked to run the same vtcal code and to see this folder
        (:func:`pipeline.batch.cluster.preflight`)
    preload : modules the process pool's fork server imports besides :data:`PRELOAD`

    Raises
    ------
    BadInput
        Unknown executor, ``workers < 1``, ``scheduler`` without Dask, Dask not
        installed, a scheduler that cannot be reached, or (with ``out_dir``) a
        cluster without workers, with other vtcal code, or not sharing ``out_dir``.
    """
    if kind not in EXECUTORS:
        raise BadInput(f"--executor {kind!r}: not one of {', '.join(EXECUTORS)}")
    if workers is not None and workers < 1:
        raise BadInput(f"--workers {workers}: needs at least 1")
    n = workers or default_workers()
    if kind == "processes":
        if scheduler:
            raise BadInput("--scheduler is for --executor dask; the process pool needs no server")
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=n, mp_context=process_context(preload)) as pool:
            yield pool
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise BadInput("--executor dask needs Dask distributed: pip install 'vtcal[dask]'") from exc
    with contextlib.ExitStack() as stack:
        if scheduler:
            try:
                client = stack.enter_context(Client(scheduler, timeout="10s"))
            except (OSError, TimeoutError) as exc:
                raise BadInput(f"--scheduler {scheduler}: cannot connect: {exc}") from exc
            if out_dir is not None:
                from pipeline.batch.cluster import preflight

                preflight(client, scheduler, out_dir)
        else:
            cluster = stack.enter_context(
                LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    host="127.0.0.1",
                    # the scheduler's HTTP server (health, metrics) serves even without
                    # the dashboard, by default on 8787: a free port instead, so that two
                    # batches at once do not collide (nor warn)
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                    # a throwaway cluster: its shutdown chatter (heartbeats to a
                    # closed scheduler) is noise; task errors come back as outcomes
                    silence_logs=logging.CRITICAL,
                    # each worker imports ``preload`` once, at its start (a batch: the
                    # lazily loaded modules and the compiled detector, RUN_PRELOAD; a
                    # cluster started apart: `dask worker --preload pipeline.batch.warm`)
                    preload=list(preload),
                )
            )
            client = stack.enter_context(Client(cluster))
        yield client.get_executor(pure=False)


def check_executor_options(kind: str, workers: int | None, scheduler: str | None) -> None:
    """Bad executor options fail before anything runs, whether or not a worker is needed."""
    if kind not in EXECUTORS:
        raise BadInput(f"--executor {kind!r}: not one of {', '.join(EXECUTORS)}")
    if workers is not None and workers < 1:
        raise BadInput(f"--workers {workers}: needs at least 1")
    if kind == "processes" and scheduler:
        raise BadInput("--scheduler is for --executor dask; the process pool needs no server")
    if kind == "dask":
        import importlib.util

        if importlib.util.find_spec("distributed") is None:
            raise BadInput("--executor dask needs Dask distributed: pip install 'vtcal[dask]'")
