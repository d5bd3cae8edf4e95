"""Batch reprocessing: many recordings through the pipeline, fanned out over an executor.

A batch is a list of :class:`BatchItem` (from paths or a dataset manifest, see
:func:`load_manifest`). Each item is one task, :func:`run_recording`, which runs
:func:`pipeline.run.orchestrator.run_pipeline` on the recording in a worker process,
into ``OUT/<name>/``, and returns a small picklable :class:`RecordingOutcome`
(status, one-line error, stage statuses, headline figures, peak RSS): no
DataFrame ever crosses the executor, the artefacts stay on disk.

Fan-out goes through the standard :class:`concurrent.futures.Executor`
interface only, so one code path serves

- local worker processes (the default: no extra dependency, no server), each a
  one-process :class:`~concurrent.futures.ProcessPoolExecutor` handed the next
  recording when it finishes one and replaced after ``recycle_after``
  recordings (a worker that dies costs only its own recording; memory a stage
  leaves behind cannot accumulate), and
- Dask distributed (``pip install vtcal[dask]``): ``Client(address).get_executor()``
  on a cluster, or a ``LocalCluster`` when no scheduler address is given.

Caching is the orchestrator's: every stage's Parquet outputs record the hashes
of their inputs, the stage configuration and the package version, and a fresh
stage is skipped. An interrupted batch therefore resumes where it stopped.
``force=True`` re-runs every stage. Before fanning out, this process asks the
run ledger (:mod:`pipeline.run.ledger`) about every recording: a run folder it
vouches for (same recording bytes, options, ``until``, code; artefacts intact)
is not sent to a worker at all, and when no recording is left the worker pool
is never started. When, in addition, ``batch.json`` says the summary and
comparison files were written by a batch with the same fingerprint and they are
intact, they are left as they are (no pandas is loaded): a batch run again with
nothing changed only re-hashes files.

A recording that fails (bad input, calibration that cannot be trusted, or an
internal error, even a worker that dies) is recorded in the summary with its
one-line error; the others carry on.

Worker processes run single-threaded numerics (``OMP_NUM_THREADS=1`` and
friends, OpenCV at one thread): the parallelism is one recording per worker,
and N workers each spawning N BLAS threads would oversubscribe the cores.

This module imports nothing heavy at module level (no numpy): the process pool's
server process sets the thread limits in its environment before numpy loads.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.batch.executor import (
    EXECUTORS,
    RUN_PRELOAD,
    THREAD_ENV,
    check_executor_options,
    default_workers,
    open_executor,
    prestart,
    process_context,
)
from pipeline.batch.manifest import NAME_OK, BatchItem, Manifest, items_from_paths, load_manifest
from pipeline.batch.outcome import (
    FIGURES_FLOAT,
    FIGURES_INT,
    RecordingOutcome,
    cached_outcome,
    interrupted_outcome,
    limit_threads,
    run_recording,
    take_result,
    worker_failure,
)
from pipeline.batch.record import BATCH_RECORD, batch_fingerprint, reusable_record, write_record
from pipeline.batch.summary import (
    compare_batch,
    compare_lines,
    identified_runs,
    summary_table,
    write_summary,
)
from pipeline.errors import BadInput, VtcalError

#: the batch's public names, importable from here (the parts: batch_manifest,
#: batch_outcome, batch_executor, batch_summary)
__all__ = [
    "EXECUTORS",
    "FIGURES_FLOAT",
    "FIGURES_INT",
    "THREAD_ENV",
    "BatchIncomplete",
    "BatchItem",
    "BatchResult",
    "Manifest",
    "RecordingOutcome",
    "compare_batch",
    "compare_lines",
    "default_workers",
    "items_from_paths",
    "limit_threads",
    "load_manifest",
    "open_executor",
    "run_batch",
    "run_recording",
    "summary_table",
    "take_result",
    "write_summary",
]

if TYPE_CHECKING:
    import pandas as pd

    from pipeline.run.orchestrator import RunConfig


class BatchIncomplete(VtcalError):
    """Some recordings of a batch failed (they are in the summary). Exit code 1."""

    exit_code = 1


# ---------------------------------------------------------------------------------------
# the batch


#: Called as each recording finishes: ``(done, total, outcome)``.
BatchProgress = Callable[[int, int, RecordingOutcome], None]


@dataclass
class BatchResult:
    """A finished batch.

    ``timings`` (s): ``fan_out`` (ledger checks, then executor start to the last
    outcome, pool shutdown included), ``summary`` (summary.parquet), ``compare``
    (compare.parquet and compare.html); ``seconds`` is the whole batch.

    ``reused`` is True when the summary and comparison files were left as an
    identical earlier batch wrote them (see :func:`run_batch`); :attr:`summary`
    then reads ``summary.parquet`` and :attr:`compare` recomputes the comparison
    (without writing) when first asked for. ``compare_lines`` are the
    comparison's printed lines (the shipped model per run, the verdict, what moved).
    """

    out_dir: Path
    outcomes: list[RecordingOutcome]
    summary_frame: pd.DataFrame | None
    summary_path: Path
    seconds: float
    interrupted: bool = False
    compare_result: Any = None
    compare_note: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    compare_lines: list[str] = field(default_factory=list)
    reused: bool = False

    @property
    def summary(self) -> pd.DataFrame:
        """The summary table (schema ``batch_summary``)."""
        if self.summary_frame is None:
            from pipeline.io.artefacts import read_artefact

            self.summary_frame = read_artefact(self.summary_path, "batch_summary")
        return self.summary_frame

    @property
    def compare(self) -> Any:
        """The :class:`pipeline.accuracy.compare.CompareResult` of the identified runs, or None."""
        if self.compare_result is None and self.reused and self.compare_lines:
            from pipeline.accuracy.compare import compare_runs

            self.compare_result = compare_runs(identified_runs(self.outcomes))
        return self.compare_result

    @property
    def n_ok(self) -> int:
        return sum(o.status == "ok" for o in self.outcomes)

    @property
    def failed(self) -> list[RecordingOutcome]:
        return [o for o in self.outcomes if o.status != "ok"]


def _check_names(items: Sequence[BatchItem]) -> None:
    names = [it.name for it in items]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise BadInput(f"batch: repeated run folder name(s) {', '.join(dup)}")
    for n in names:
        if not NAME_OK.match(n):
            raise BadInput(f"batch: run folder name {n!r} is not a plain folder name")


class _Slot:
    """Somewhere to submit tasks: an executor, how many tasks it may hold at once,
    and (for our own one-worker process pools) when to replace it.

    ``make`` builds a fresh executor (None for an executor we were given, which is
    never replaced nor shut down here). A slot of capacity 1 with its own
    one-process pool isolates its task: a worker that dies takes down that task
    only, and replacing the pool after ``recycle_after`` tasks bounds the memory a
    long-lived worker could accumulate.
    """

    def __init__(
        self,
        executor: Executor | None,
        capacity: int,
        make: Callable[[], Executor] | None = None,
        recycle_after: int = 0,
    ) -> None:
        self.executor = executor
        self.capacity = capacity
        self.make = make
        self.recycle_after = recycle_after
        self.in_flight = 0
        self.used = 0

    def free(self) -> bool:
        return self.in_flight < self.capacity

    def submit(self, *args: Any) -> Future[RecordingOutcome]:
        if self.make is not None and (
            self.executor is None or (self.recycle_after and self.used >= self.recycle_after)
        ):
            self.close(wait=True)
            self.executor = self.make()
            self.used = 0
        assert self.executor is not None
        fut = self.executor.submit(run_recording, *args)
        self.in_flight += 1
        self.used += 1
        return fut

    def broken(self) -> None:
        """Its pool broke (a worker died): start afresh at the next submit."""
        self.close(wait=False)

    def close(self, wait: bool = True) -> None:
        if self.make is not None and self.executor is not None:
            self.executor.shutdown(wait=wait, cancel_futures=True)
            self.executor = None

    def abort(self, grace_s: float = 10.0) -> None:
        """After Ctrl-C: stop our pool without waiting on its worker for ever.

        The worker got the same SIGINT and normally hands its interrupted task
        back at once; one interrupted inside a C extension (or an import) may
        never do so, and ``shutdown(wait=True)`` would then hang the batch. Its
        process is given ``grace_s`` to end, then terminated (killed if that is not
        enough within ``grace_s``). Its recording is
        unfinished either way (atomic writes: nothing half-written stays; the
        next run redoes it).
        """
        if self.make is None or self.executor is None:
            return
        procs = list((getattr(self.executor, "_processes", None) or {}).values())
        self.executor.shutdown(wait=False, cancel_futures=True)
        self.executor = None
        for proc in procs:
            proc.join(grace_s)
            if proc.is_alive():
                proc.terminate()
                proc.join(grace_s)
            if proc.is_alive():  # SIGTERM not acted on in time (a loaded machine): SIGKILL
                proc.kill()
                proc.join(grace_s)


def run_batch(
    items: Sequence[BatchItem],
    out: str | os.PathLike[str],
    config: RunConfig | None = None,
    *,
    executor: Executor | None = None,
    kind: str = "processes",
    workers: int | None = None,
    scheduler: str | None = None,
    until: str | None = None,
    force: bool = False,
    progress: BatchProgress | None = None,
    compare: bool = True,
    recycle_after: int = 10,
) -> BatchResult:
    """Run every recording through the pipeline into ``out/<item.name>/``, then summarise.

    Parameters
    ----------
    items : the recordings (:func:`items_from_paths`, :func:`load_manifest`)
    out : batch folder (created); ``out/summary.parquet`` is the summary
    config : stage options for every recording (:class:`pipeline.run.orchestrator.RunConfig`)
    executor : an open executor to use (left open; every task is submitted to it at
        once); without it one is opened from ``kind``, ``workers``, ``scheduler``:
        for ``"processes"``, ``workers`` one-process pools fed one recording at a
        time, for ``"dask"`` :func:`open_executor`
    until, force : passed to every :func:`~pipeline.run.orchestrator.run_pipeline`
    progress : called in this process as each recording finishes
    compare : also write the cross-run comparison of the identified runs
        (``compare.parquet``, ``compare.html``, see :func:`compare_batch`)
    recycle_after : with ``"processes"``, replace a worker process after this
        many recordings (0: never), so that memory a stage leaves behind cannot
        accumulate over hundreds of recordings. A worker that dies (crash, out of
        memory) costs only its own recording, which is run once more in a fresh
        worker (``retried``).

    Returns
    -------
    BatchResult; its outcomes are in the order of ``items``; ``compare`` holds the
    :class:`pipeline.accuracy.compare.CompareResult` (or None, ``compare_note`` says why). On
    Ctrl-C the summary of what finished is written (the rest ``not_run``) before
    :class:`KeyboardInterrupt` propagates; finished recordings are cached for the next run.

    Notes
    -----
    Without ``force``, a recording whose run folder the run ledger vouches for
    (:func:`cached_outcome`) is answered in this process and never sent to a
    worker; the process pool (or Dask cluster) is started only when some
    recording is left. When every recording was answered so and ``batch.json``
    records a batch with the same items, options, ``until`` and runs whose
    summary and comparison files are intact, those files are not rewritten:
    ``summary.parquet``'s per-run columns (stages, times, worker) then describe
    the batch that last wrote it.
    """
    _check_request(items, until, recycle_after, executor, kind, workers, scheduler)
    out_dir = Path(out).expanduser().absolute()
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    items = [
        BatchItem(
            it.name, Path(it.recording).expanduser().absolute(), it.robot, it.notes, it.simulate
        )
        for it in items
    ]
    outcomes: dict[str, RecordingOutcome] = {}
    timings: dict[str, float] = {}
    pending, interrupted = _run_pending(
        items, out_dir, config, until, force, outcomes, progress,
        executor, kind, workers, scheduler, recycle_after,
    )  # fmt: skip
    timings["fan_out"] = time.perf_counter() - t0
    ordered = [outcomes.get(it.name) or interrupted_outcome(it, out_dir) for it in items]
    fp = None if interrupted else batch_fingerprint(out_dir, items, ordered, config, until, compare)
    path = out_dir / "summary.parquet"
    if not pending and fp is not None:
        kept = reusable_record(out_dir, fp)
        if kept is not None:  # nothing changed since the batch that wrote these files
            timings["summary"] = timings["compare"] = 0.0
            seconds = time.perf_counter() - t0
            note, lines = str(kept.get("compare_note", "")), list(kept.get("compare_lines", []))
            return BatchResult(
                out_dir, ordered, None, path, seconds, False, None, note, timings, lines, True
            )
    (out_dir / BATCH_RECORD).unlink(missing_ok=True)  # it vouches for the files below
    summary = summary_table(ordered)
    path = write_summary(out_dir, summary, config=config, until=until, force=force)
    timings["summary"] = time.perf_counter() - t0 - timings["fan_out"]
    if interrupted:
        raise KeyboardInterrupt
    t1 = time.perf_counter()
    cmp, note = compare_batch(out_dir, ordered) if compare else (None, "not asked for")
    lines = compare_lines(cmp) if cmp is not None else []
    timings["compare"] = time.perf_counter() - t1
    if fp is not None:
        written = [path] + ([out_dir / "compare.parquet", out_dir / "compare.html"] if cmp else [])
        write_record(out_dir, fp, written, note, lines)
    seconds = time.perf_counter() - t0
    return BatchResult(out_dir, ordered, summary, path, seconds, False, cmp, note, timings, lines)


def _check_request(
    items: Sequence[BatchItem],
    until: str | None,
    recycle_after: int,
    executor: Executor | None,
    kind: str,
    workers: int | None,
    scheduler: str | None,
) -> None:
    """Step 1 of :func:`run_batch`: refuse bad names, stages and executor options (BadInput)."""
    _check_names(items)
    if until is not None:
        from pipeline.run.orchestrator import STAGES

        if until not in STAGES:
            raise BadInput(f"--until {until!r}: not a stage (stages: {', '.join(STAGES)})")
    if recycle_after < 0:
        raise BadInput(f"--recycle {recycle_after}: must be >= 0")
    if executor is None:
        check_executor_options(kind, workers, scheduler)


def _run_pending(
    items: Sequence[BatchItem],
    out_dir: Path,
    config: RunConfig | None,
    until: str | None,
    force: bool,
    outcomes: dict[str, RecordingOutcome],
    progress: BatchProgress | None,
    executor: Executor | None,
    kind: str,
    workers: int | None,
    scheduler: str | None,
    recycle_after: int,
) -> tuple[list[BatchItem], bool]:
    """Steps 2 and 3 of :func:`run_batch` into ``outcomes``: (items left for the workers, Ctrl-C)."""
    pending: list[BatchItem] = []
    try:
        pending = _from_ledgers(
            items, out_dir, config, until, force, executor, kind, outcomes, progress
        )
        if pending:
            with contextlib.ExitStack() as stack:
                slots = _open_slots(
                    stack, executor, kind, workers, scheduler, out_dir, len(pending), recycle_after
                )
                try:
                    _fan_out(
                        slots, pending, out_dir, config, until, force, outcomes, progress,
                        len(items),
                    )  # fmt: skip
                except KeyboardInterrupt:
                    for slot in slots:
                        slot.abort()
                    raise
    except KeyboardInterrupt:
        return pending, True
    return pending, False


def _from_ledgers(
    items: Sequence[BatchItem],
    out_dir: Path,
    config: RunConfig | None,
    until: str | None,
    force: bool,
    executor: Executor | None,
    kind: str,
    outcomes: dict[str, RecordingOutcome],
    progress: BatchProgress | None,
) -> list[BatchItem]:
    """Step 2: answer from the run ledgers in this process; the items left for the workers.

    The worker pool is prestarted at the first item left, so that its imports
    overlap the remaining ledger checks.
    """
    pending: list[BatchItem] = []
    for it in items:  # the run ledger, in this process: no worker for what is done
        rec = None if force else cached_outcome(it, out_dir / it.name, config, until)
        if rec is None:
            if not pending and executor is None:
                prestart(kind, RUN_PRELOAD)  # its imports overlap the ledger checks
            pending.append(it)
            continue
        outcomes[it.name] = rec
        if progress is not None:
            progress(len(outcomes), len(items), rec)
    return pending


def _open_slots(
    stack: contextlib.ExitStack,
    executor: Executor | None,
    kind: str,
    workers: int | None,
    scheduler: str | None,
    out_dir: Path,
    n_pending: int,
    recycle_after: int,
) -> list[_Slot]:
    """Step 3: where the pending recordings run (closed with ``stack``).

    A given executor takes them all; ``"processes"``: one-process pools, one
    recording at a time each, recycled after ``recycle_after``; ``"dask"``:
    :func:`open_executor`.
    """
    if executor is not None:
        return [_Slot(executor, max(1, n_pending))]
    if kind == "processes":
        ctx = process_context(RUN_PRELOAD)
        n = min(workers or default_workers(), n_pending)

        def make() -> Executor:
            from concurrent.futures import ProcessPoolExecutor

            return ProcessPoolExecutor(max_workers=1, mp_context=ctx)

        slots = [_Slot(None, 1, make, recycle_after) for _ in range(n)]
        for slot in slots:
            stack.callback(slot.close)
        return slots
    ex = stack.enter_context(open_executor(kind, workers, scheduler, out_dir, RUN_PRELOAD))
    return [_Slot(ex, max(1, n_pending))]


def _fan_out(
    slots: list[_Slot],
    items: Sequence[BatchItem],
    out_dir: Path,
    config: RunConfig | None,
    until: str | None,
    force: bool,
    outcomes: dict[str, RecordingOutcome],
    progress: BatchProgress | None,
    total: int | None = None,
) -> None:
    """Feed the items to the slots as they free up; collect outcomes as tasks finish.

    ``progress`` counts ``outcomes`` (which may already hold some) out of ``total``
    (default: the number of ``items``).

    A task whose worker died (:class:`~concurrent.futures.BrokenExecutor`) is run
    once more in a fresh worker when its slot can make one, else recorded as an
    internal error; any other failure to return is recorded as such.
    """
    from collections import deque
    from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, wait

    queue = deque(items)
    total = len(items) if total is None else total
    attempts: dict[str, int] = {}
    in_flight: dict[Future[RecordingOutcome], tuple[_Slot, BatchItem]] = {}

    def finish(it: BatchItem, rec: RecordingOutcome) -> None:
        rec.retried = attempts.get(it.name, 1) > 1
        outcomes[it.name] = rec
        if progress is not None:
            progress(len(outcomes), total, rec)

    def died(slot: _Slot, it: BatchItem, exc: BaseException) -> None:
        slot.broken()
        if slot.make is not None and attempts[it.name] < 2:
            queue.appendleft(it)
        else:
            finish(it, worker_failure(it, out_dir / it.name, exc))

    try:
        while queue or in_flight:
            for slot in slots:
                while queue and slot.free():
                    it = queue.popleft()
                    attempts[it.name] = attempts.get(it.name, 0) + 1
                    try:
                        fut = slot.submit(it, str(out_dir / it.name), config, until, force)
                    except BrokenExecutor as exc:
                        died(slot, it, exc)
                        if slot.make is None:
                            continue
                        break
                    in_flight[fut] = (slot, it)
            if not in_flight:
                continue
            done, _ = wait(list(in_flight), return_when=FIRST_COMPLETED)
            for fut in done:
                slot, it = in_flight.pop(fut)
                slot.in_flight -= 1
                try:
                    rec = fut.result()
                except BrokenExecutor as exc:
                    died(slot, it, exc)
                    continue
                except Exception as exc:  # dask: KilledWorker, pickling, ...
                    rec = worker_failure(it, out_dir / it.name, exc)
                finish(it, rec)
    except BaseException:
        for fut in in_flight:
            fut.cancel()
        raise


# ---------------------------------------------------------------------------------------
# the summary
