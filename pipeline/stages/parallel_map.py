"""``parallel_map``: a map over a few independent CPU-bound tasks, forked when cores are free.

For work whose tasks each take a fair fraction of a second (cross-validating
one error model: a few dozen identifications). With ``n`` workers, this process
and ``n - 1`` forked children take the tasks in their order by a shared index
(:func:`_drain`); the children inherit the function and its data (nothing is
pickled but their results), so the closure may hold data frames and fitted
models. This process works rather than waits: one fork fewer, and its share runs
with warm caches (a forked child's first touches of inherited memory copy pages).
UR5e-like cell, fresh runs in alternating pairs: identification 0.30-0.41 ->
0.27-0.34 s, cross-validation 0.31-0.42 -> 0.26-0.36 s (docs/speed.md).
The results come back in the order of the tasks, and are those of the serial
map: each task runs the same code on the same inputs.

It runs serially when asked to (``workers=1``), when there is one task, where
forking is unavailable or not allowed (a daemonic process such as a
``vtcal batch`` worker may not have children), and when ``workers=0`` (auto)
finds no core to spare or runs in a child process (a ``vtcal batch`` or Dask
worker: the batch already uses the cores, one recording per worker).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.pool
import os
import time
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

#: the function the forked children call (set just before the fork, inherited)
_TASK: Callable[[Any], Any] | None = None


#: probes of the cores this run keeps busy beside its own process right now (each says
#: how many), e.g. the warm report process reading frames (:mod:`pipeline.report.warm`)
_BUSY: list[Callable[[], int]] = []


def register_busy(probe: Callable[[], int]) -> None:
    """Have :func:`free_workers` leave out the cores ``probe()`` says are busy now."""
    _BUSY.append(probe)


def unregister_busy(probe: Callable[[], int]) -> None:
    """Undo :func:`register_busy` (no error if it was not registered)."""
    if probe in _BUSY:
        _BUSY.remove(probe)


def free_workers(limit: int = 2, *, count_busy: bool = True) -> int:
    """Processes worth starting now: cores not busy, at most ``limit``.

    By the 1-minute load, ``os.cpu_count() - load + 1`` rounded to the nearest, at
    least 1 (this process itself): a core counts as free when the load leaves at
    least half of it. (Rounded down, an idle 2-core machine whose load average reads
    0.93-1.01 while vmstat shows it 99-100 % idle forked or not at random.) A load
    average lags: vtcal runs one after another leave it at 1.4-1.6 on an idle 2-core
    machine for a minute, and the next run then started no warm report and fitted in
    one process (its report 0.5-0.77 s instead of 0.2). So where the kernel tells
    how many tasks are runnable right now (:func:`runnable_others`), the cores no
    other task wants at this moment count as free as well: the larger of the two
    counts is taken. Work this run has started beside it (:func:`register_busy`) is
    then left out: measured, the UR5e-like cell's identification took 0.19-0.24 s
    in two processes while the warm report process read frames, 0.14-0.16 s in one.
    """
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover - no load average on this platform
        return 1
    n = int(cores - load + 1.5)
    others = runnable_others()
    if others is not None:
        n = max(n, cores - others)
    busy = sum(max(0, int(probe())) for probe in list(_BUSY)) if count_busy else 0
    return max(1, min(limit, n) - busy)


def runnable_others(samples: int = 3, gap_s: float = 0.0005) -> int | None:
    """Tasks other than this one runnable now: the largest of a few readings of the
    fourth field of ``/proc/loadavg`` (``runnable/total``, this reading thread among
    the runnable) minus one; None where there is no such file (not Linux)."""
    seen = []
    try:
        for i in range(samples):
            with open("/proc/loadavg", encoding="ascii") as f:
                seen.append(int(f.read().split()[3].split("/")[0]))
            if i + 1 < samples:
                time.sleep(gap_s)
    except (OSError, ValueError, IndexError):
        return None
    return max(0, max(seen) - 1)


#: the tasks and the shared index of the next one (set just before the fork, inherited)
_TASKS: Sequence[Any] | None = None
_NEXT: Any = None


def _drain() -> list[tuple[int, Any]]:
    """Take tasks by the shared index until none is left; ``(index, result)`` of each.

    Run by every child and by this process itself, so a fast worker takes more tasks
    (the order they are taken in is the tasks' order: put the longest first).
    """
    assert _TASK is not None and _TASKS is not None and _NEXT is not None
    out: list[tuple[int, Any]] = []
    while True:
        with _NEXT.get_lock():
            i = _NEXT.value
            _NEXT.value = i + 1
        if i >= len(_TASKS):
            return out
        out.append((i, _TASK(_TASKS[i])))


#: how often (s) a wait for a child's results checks that the children are alive
LIVENESS_S = 0.25


def _collect(
    pending: multiprocessing.pool.AsyncResult,  # type: ignore[type-arg]
    children: list[Any],
    done: dict[int, Any],
) -> bool:
    """Wait for one child's results into ``done``; False as soon as a child has died.

    A child killed mid-task (out of memory, a signal, a crash in compiled code) never
    sends its results, and the pool replaces it without telling: a plain ``get()``
    would wait for ever. Every :data:`LIVENESS_S` the children's exit codes are read
    (a child only exits when the pool is closed).
    """
    while True:
        try:
            done.update(pending.get(timeout=LIVENESS_S))
            return True
        except multiprocessing.TimeoutError:
            if any(c.exitcode is not None for c in children):
                return False


def parallel_map(
    fn: Callable[[T], R], tasks: Sequence[T], workers: int = 1, *, yield_to_busy: bool = True
) -> list[R]:
    """``[fn(t) for t in tasks]``, in up to ``workers`` forked processes (0: auto).

    Parameters
    ----------
    fn : the task function (a closure is fine: children inherit it by fork)
    tasks : the task arguments (picklable), results come back in their order
    workers : processes; 1 serial, 0 :func:`free_workers`
    yield_to_busy : with ``workers=0``, leave out the cores this run keeps busy beside
        it (:func:`register_busy`). Identification yields (five short fits: forked onto
        a busy core they took 0.19-0.24 s on the UR5e-like cell, in this process alone
        0.14-0.16 s); cross-validation does not (32 refits: the warm report's reading
        often still runs when it starts, and alone they took 0.26-0.33 s (eight runs) against
        0.18-0.27 s in two processes beside it)

    Returns
    -------
    list of results, as the serial map's (a result that cannot be pickled back from a
    child makes the whole map run again serially; the tasks of a child that died are
    run again in this process)
    """
    global _TASK
    if workers == 0:
        n = (
            1
            if multiprocessing.parent_process() is not None
            else free_workers(count_busy=yield_to_busy)
        )
    else:
        n = workers
    n = min(n, len(tasks))
    if (
        n <= 1
        or multiprocessing.current_process().daemon
        or "fork" not in multiprocessing.get_all_start_methods()
    ):
        return [fn(t) for t in tasks]
    global _NEXT, _TASKS
    ctx = multiprocessing.get_context("fork")
    _TASK, _TASKS, _NEXT = fn, tasks, ctx.Value("i", 0)
    try:
        with ctx.Pool(n - 1) as pool:  # this process is the n-th worker
            children = list(pool._pool)  # type: ignore[attr-defined]
            pending = [pool.apply_async(_drain) for _ in range(n - 1)]
            done = dict(_drain())
            for p in pending:
                if not _collect(p, children, done):
                    break  # a child died holding tasks: the rest below, in this process
        # tasks a dead child had taken (none when every child came back)
        for i in range(len(tasks)):
            if i not in done:
                done[i] = fn(tasks[i])
        return [done[i] for i in range(len(tasks))]
    except multiprocessing.pool.MaybeEncodingError:  # type: ignore[attr-defined]
        # a result the children cannot send back (an object of a class defined inside a
        # function, say): the map again, in this process
        return [fn(t) for t in tasks]
    finally:
        _TASK, _TASKS, _NEXT = None, None, None
