"""Where the audit's tasks run: in this process, or on the batch's engine.

``vtcal audit --executor processes|dask [--scheduler ADDR] [--workers N]`` takes the
options of ``vtcal batch`` and the same executors (:func:`pipeline.batch.executor.open_executor`:
a pool of single-threaded processes forked from a warm fork server, a local Dask
cluster, or the Dask cluster a fleet's recordings ran on). Tasks go in chunks
(:func:`chunk_size`: a few per worker, at most :data:`MAX_CHUNK` tasks each), at most
:data:`IN_FLIGHT` chunks per worker at once, so that neither the pool's queue nor the
Dask scheduler holds the whole fleet's inputs. Results come back with their task's
index, in the order they finish. One worker with the process pool runs the tasks in
this process (no pool); no task starts no pool, no cluster.

A task runs the same code on the same inputs wherever it runs; a worker reads its
recording's touch-ups itself (:func:`pipeline.audit.identity.with_table`), so the
workers of a cluster started apart must see the run folders at the same paths.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

#: tasks per chunk at most (a fit or a held-out figure at touch-up level: 0.02-0.1 s)
MAX_CHUNK = 8
#: chunks a worker may have queued or running at once
IN_FLIGHT = 3
#: what the process pool's fork server imports for the audit (its workers start warm)
PRELOAD = ("pipeline.audit.work", "pipeline.audit.pairs", "pipeline.audit.fit")


def chunk_size(n_tasks: int, workers: int) -> int:
    """Tasks per chunk: about eight chunks per worker, 1 .. :data:`MAX_CHUNK`."""
    return max(1, min(MAX_CHUNK, math.ceil(n_tasks / (8 * max(1, workers)))))


def _run_chunk(fn: Callable[[Any], Any], chunk: Sequence[Any]) -> list[Any]:
    return [fn(t) for t in chunk]


def resolve_workers(kind: str, workers: int | None) -> int:
    """Workers to use: ``workers``, or (None, 0) the free cores for the process pool
    (:func:`pipeline.stages.parallel_map.free_workers`), the usable cores for Dask."""
    from pipeline.batch.executor import default_workers

    if workers:
        return workers
    if kind == "processes":
        from pipeline.stages.parallel_map import free_workers

        return free_workers(limit=default_workers())
    return default_workers()


def prestart(kind: str, workers: int | None) -> None:
    """Start the process pool's fork server now (its imports overlap this process's)
    unless the audit runs in this process."""
    if kind == "processes" and workers != 1:
        from pipeline.batch.executor import prestart as start

        start(kind, PRELOAD)


class Engine:
    """The executor of one audit: opened at its first task, shut down on exit.

    Parameters
    ----------
    kind, workers, scheduler : as ``vtcal batch`` (:func:`pipeline.batch.executor.open_executor`)
    out_dir : the audit folder (with a ``scheduler``: the cluster is first checked to run
        this vtcal and to see it, :func:`pipeline.batch.cluster.preflight`)
    """

    def __init__(
        self,
        kind: str = "processes",
        workers: int | None = 1,
        scheduler: str | None = None,
        out_dir: Path | None = None,
    ) -> None:
        from pipeline.batch.executor import check_executor_options

        check_executor_options(kind, workers or None, scheduler)
        self.kind, self.scheduler, self.out_dir = kind, scheduler, out_dir
        self.workers = resolve_workers(kind, workers)
        self._stack = contextlib.ExitStack()
        self._executor: Any = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()
        self._executor = None

    @property
    def serial(self) -> bool:
        return self.kind == "processes" and self.workers <= 1

    def _open(self) -> Any:
        if self._executor is None:
            from pipeline.batch.executor import open_executor

            out = self.out_dir if self.scheduler else None
            if out is not None:
                out.mkdir(parents=True, exist_ok=True)
            self._executor = self._stack.enter_context(
                open_executor(self.kind, self.workers, self.scheduler, out, PRELOAD)
            )
        return self._executor

    def imap(
        self, fn: Callable[[Any], Any], tasks: Sequence[Any], max_chunk: int = MAX_CHUNK
    ) -> Iterator[tuple[int, Any]]:
        """``(index, fn(tasks[index]))`` of every task, as they finish (``fn``: a module-level
        function, sent by reference; at most ``max_chunk`` tasks per chunk)."""
        if not tasks:
            return
        if self.serial or (self.kind == "processes" and len(tasks) == 1):
            for i, t in enumerate(tasks):
                yield i, fn(t)
            return
        from concurrent.futures import FIRST_COMPLETED, wait

        ex = self._open()
        size = min(max_chunk, chunk_size(len(tasks), self.workers))
        starts = iter(range(0, len(tasks), size))
        in_flight: dict[Any, int] = {}
        while True:
            while len(in_flight) < IN_FLIGHT * self.workers:
                s = next(starts, None)
                if s is None:
                    break
                in_flight[ex.submit(_run_chunk, fn, tasks[s : s + size])] = s
            if not in_flight:
                return
            done, _ = wait(list(in_flight), return_when=FIRST_COMPLETED)
            for fut in done:
                s = in_flight.pop(fut)
                for j, r in enumerate(fut.result()):
                    yield s + j, r
