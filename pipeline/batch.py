"""Batch reprocessing: many recordings through the pipeline, fanned out over an executor.

A batch is a list of :class:`BatchItem` (from paths or a dataset manifest, see
:func:`load_manifest`). Each item is one task, :func:`run_recording`, which runs
:func:`pipeline.orchestrator.run_pipeline` on the recording in a worker process,
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
run ledger (:mod:`pipeline.run_ledger`) about every recording: a run folder it
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
import json
import logging
import os
import re
import socket
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.errors import BadInput, CalibrationFailed, VtcalError

if TYPE_CHECKING:
    import pandas as pd

    from pipeline.orchestrator import RunConfig

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
_PRELOAD = (
    "pipeline.batch",
    "pipeline.orchestrator",
    "pipeline.stages.ingest",
    "pipeline.stages.detect",
    "pipeline.stages.touchup",
    "pipeline.stages.outliers",
    "pipeline.stages.identify",
    "pipeline.stages.crossval",
)

#: Headline figures copied from ``identify.json`` into the summary (same names there).
_FIGURES_INT = ("n_rows", "n_used", "n_targets", "n_identified", "n_params")
_FIGURES_FLOAT = (
    "rms_mm",
    "max_mm",
    "predicted_shape_rms_mm",
    "predicted_absolute_rms_mm",
    "cond",
)


class BatchIncomplete(VtcalError):
    """Some recordings of a batch failed (they are in the summary). Exit code 1."""

    exit_code = 1


# ---------------------------------------------------------------------------------------
# what a batch is made of


@dataclass(frozen=True)
class BatchItem:
    """One recording of a batch.

    Attributes
    ----------
    name : run folder name under the batch output folder (unique within the batch)
    recording : path of the MCAP recording (absolute once resolved)
    robot : robot the manifest says recorded it ('' when not given)
    notes : free text from the manifest
    """

    name: str
    recording: Path
    robot: str = ""
    notes: str = ""


@dataclass(frozen=True)
class Manifest:
    """A dataset manifest: ``datasets/NAME.toml``."""

    path: Path
    name: str
    description: str
    items: tuple[BatchItem, ...]


_NAME_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def _unique_names(stems: Sequence[str]) -> list[str]:
    """Make run folder names unique in order: ``a, a, b -> a, a-2, b``.

    The first occurrence keeps its stem; a repeat gets the smallest ``-k`` suffix
    that is neither another stem nor already used.
    """
    taken = set(stems)
    used: set[str] = set()
    out = []
    for s in stems:
        name, k = s, 1
        while name in used or (k > 1 and name in taken):
            k += 1
            name = f"{s}-{k}"
        used.add(name)
        out.append(name)
    return out


def items_from_paths(paths: Sequence[str | os.PathLike[str]]) -> list[BatchItem]:
    """Batch items for recordings given on the command line.

    Each is named after the file stem (``cell3.mcap -> cell3``); repeated stems get
    ``-2``, ``-3``... in the order given. Missing files are not an error here:
    they fail in their own task and show in the summary.
    """
    ps = [Path(p).expanduser().absolute() for p in paths]
    names = _unique_names([p.stem or "recording" for p in ps])
    return [BatchItem(n, p) for n, p in zip(names, ps, strict=True)]


def load_manifest(path: str | os.PathLike[str]) -> Manifest:
    """Read a dataset manifest (TOML).

    Format (paths relative to the manifest's folder)::

        name = "fleet_demo"
        description = "..."

        [[recordings]]
        path = "fleet_demo/cell1.mcap"   # required
        name = "cell1"                   # optional run folder name (default: file stem)
        robot = "lrmate"                 # optional
        notes = "after the J2 gearbox swap"   # optional

    Raises
    ------
    BadInput
        One line naming the manifest and what is wrong (unreadable TOML, no
        ``[[recordings]]``, an entry without ``path``, a bad or repeated ``name``).
    """
    import tomllib

    p = Path(path)
    if not p.is_file():
        raise BadInput(f"{p}: no such manifest file")
    try:
        raw = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BadInput(f"{p}: not a readable TOML manifest: {exc}") from exc
    recs = raw.get("recordings")
    if not isinstance(recs, list) or not recs:
        raise BadInput(f"{p}: no [[recordings]] entries")
    base = p.parent.absolute()
    paths: list[Path] = []
    given: list[str | None] = []
    extra: list[tuple[str, str]] = []
    for i, r in enumerate(recs):
        where = f"{p}: recordings[{i}]"
        if not isinstance(r, dict) or not isinstance(r.get("path"), str) or not r["path"]:
            raise BadInput(f"{where}: needs a 'path' string")
        unknown = set(r) - {"path", "name", "robot", "notes"}
        if unknown:
            raise BadInput(f"{where}: unknown key(s) {', '.join(sorted(unknown))}")
        for key in ("name", "robot", "notes"):
            if key in r and not isinstance(r[key], str):
                raise BadInput(f"{where}: '{key}' must be a string, got {r[key]!r}")
        if "name" in r and not _NAME_OK.match(r["name"]):
            raise BadInput(f"{where}: name {r['name']!r} is not a plain folder name")
        rp = Path(r["path"]).expanduser()
        paths.append(rp if rp.is_absolute() else base / rp)
        given.append(r.get("name"))
        extra.append((r.get("robot", ""), r.get("notes", "")))
    explicit = [g for g in given if g]
    dup = sorted({g for g in explicit if explicit.count(g) > 1})
    if dup:
        raise BadInput(f"{p}: repeated recording name(s) {', '.join(dup)}")
    names = _unique_names([g or q.stem for g, q in zip(given, paths, strict=True)])
    items = tuple(
        BatchItem(n, q, robot, notes)
        for n, q, (robot, notes) in zip(names, paths, extra, strict=True)
    )
    return Manifest(
        path=p,
        name=str(raw.get("name", p.stem)),
        description=str(raw.get("description", "")),
        items=items,
    )


# ---------------------------------------------------------------------------------------
# the worker task


@dataclass
class RecordingOutcome:
    """What one task reports back: small and picklable (no tables).

    ``status`` is ``"ok"``, ``"error"`` (the recording failed; ``error_kind`` is
    ``bad_input``, ``calibration_failed``, ``error`` or ``internal``) or
    ``"not_run"`` (the batch was interrupted before it finished).
    """

    name: str
    recording: str
    run_dir: str
    robot: str = ""
    notes: str = ""
    status: str = "not_run"
    error_kind: str = ""
    error: str = ""
    exit_code: int = 0
    stages: list[tuple[str, str, float]] = field(default_factory=list)
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    peak_rss_mb: float | None = None
    rss_mb: float | None = None
    worker: str = ""
    robot_urdf: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    headline: list[str] = field(default_factory=list)
    retried: bool = False


def limit_threads() -> None:
    """Keep this process's numeric libraries to one thread each.

    The environment variables only act on libraries not yet loaded (they are set
    before numpy loads in the process pool's server); OpenCV is told directly.
    """
    os.environ.update(THREAD_ENV)
    with contextlib.suppress(Exception):
        import cv2

        cv2.setNumThreads(1)


def peak_rss_mb() -> float | None:
    """Peak resident set size of this process so far, MB (``getrusage``; None where absent)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - not on POSIX
        return None
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / (1024.0 * 1024.0) if sys.platform == "darwin" else kb / 1024.0


def rss_mb() -> float | None:
    """Resident set size of this process now, MB (``/proc/self/statm``; None elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / (1024.0 * 1024.0)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def internal_error_line(exc: BaseException) -> str:
    """``Type: message (file:line)`` of the innermost frame, as the CLI reports bugs."""
    where = exc.__traceback__
    while where is not None and where.tb_next is not None:
        where = where.tb_next
    loc = f" ({where.tb_frame.f_code.co_filename}:{where.tb_lineno})" if where else ""
    return _one_line(f"{type(exc).__name__}: {exc}{loc}")


def _error_kind(exc: VtcalError) -> str:
    if isinstance(exc, BadInput):
        return "bad_input"
    if isinstance(exc, CalibrationFailed):
        return "calibration_failed"
    return "error"


def _robot_from_urdf(run_dir: Path) -> str:
    """The ``<robot name=...>`` of the URDF the recording carried (from recording.json)."""
    try:
        urdf = json.loads((run_dir / "recording.json").read_text()).get("urdf", "")
    except (OSError, ValueError):
        return ""
    m = re.search(r"<robot\b[^>]*\bname\s*=\s*[\"']([^\"']*)[\"']", urdf or "")
    return m.group(1) if m else ""


def run_recording(
    item: BatchItem,
    run_dir: str | os.PathLike[str],
    config: RunConfig | None = None,
    until: str | None = None,
    force: bool = False,
) -> RecordingOutcome:
    """Run one recording through the pipeline; the task a batch sends to its workers.

    Never raises for a failing recording: the error becomes the outcome's
    ``status="error"`` with a one-line ``error`` (the :class:`VtcalError` message,
    or ``Type: message (file:line)`` for an internal error).

    Parameters
    ----------
    item : the recording and its manifest facts
    run_dir : run folder for its artefacts (created)
    config, until, force : passed to :func:`pipeline.orchestrator.run_pipeline`

    Returns
    -------
    RecordingOutcome with the stage statuses, wall time, this worker's peak RSS so
    far and, when identify ran or was cached, the headline figures of ``identify.json``.
    """
    limit_threads()
    out = Path(run_dir)
    rec = _new_outcome(item, out)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        from pipeline.orchestrator import run_pipeline

        result = run_pipeline(item.recording, out, config, until=until, force=force)
    except VtcalError as exc:
        rec.status, rec.error_kind = "error", _error_kind(exc)
        rec.error, rec.exit_code = _one_line(str(exc)), exc.exit_code
    except (Exception, SystemExit) as exc:  # a bug in a stage: reported, the batch goes on
        rec.status, rec.error_kind = "error", "internal"
        rec.error, rec.exit_code = internal_error_line(exc), 70
    else:
        _take_result(rec, result)
    return _close_outcome(rec, out, t0, c0)


def cached_outcome(
    item: BatchItem,
    run_dir: str | os.PathLike[str],
    config: RunConfig | None = None,
    until: str | None = None,
) -> RecordingOutcome | None:
    """The outcome of a recording whose run folder the run ledger vouches for, else None.

    Asked in the batch's own process before fanning out: what
    :func:`run_recording` would report for a run with every stage cached, made
    without a worker and without loading pandas or a stage module
    (:func:`pipeline.orchestrator.cached_run`). ``worker`` and the memory figures
    are this process's.
    """
    from pipeline.orchestrator import cached_run

    out = Path(run_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    result = cached_run(item.recording, out, config, until=until)
    if result is None:
        return None
    rec = _new_outcome(item, out)
    _take_result(rec, result)
    return _close_outcome(rec, out, t0, c0)


def _new_outcome(item: BatchItem, out: Path) -> RecordingOutcome:
    return RecordingOutcome(
        name=item.name,
        recording=str(item.recording),
        run_dir=str(out),
        robot=item.robot,
        notes=item.notes,
        worker=f"{socket.gethostname()}:{os.getpid()}",
    )


def _take_result(rec: RecordingOutcome, result: Any) -> None:
    """Stage statuses and, when identify ran or was cached, the figures of ``identify.json``."""
    rec.status = "ok"
    rec.stages = [(s.stage, s.status, float(s.seconds)) for s in result.stages]
    if any(s.stage == "identify" for s in result.stages):
        summ = result.summary
        rec.figures = {"model": summ.get("best_model") or summ.get("model")}
        rec.figures["scale_identified"] = (
            None if "scale_held" not in summ else not bool(summ["scale_held"])
        )
        for k in _FIGURES_INT + _FIGURES_FLOAT:
            v = summ.get(k)
            rec.figures[k] = v if isinstance(v, (int, float)) else None
        rec.headline = [str(h) for h in summ.get("headline", [])]


def _close_outcome(rec: RecordingOutcome, out: Path, t0: float, c0: float) -> RecordingOutcome:
    rec.seconds = time.perf_counter() - t0
    rec.cpu_seconds = time.process_time() - c0
    rec.robot_urdf = _robot_from_urdf(out)
    rec.peak_rss_mb = peak_rss_mb()
    rec.rss_mb = rss_mb()
    return rec


# ---------------------------------------------------------------------------------------
# executors


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


def _process_context() -> Any:
    """Multiprocessing context for the pool: a fork server, warm and single-threaded.

    The fork server is a fresh interpreter started with :data:`THREAD_ENV` in its
    environment; it imports the pipeline once (:data:`_PRELOAD`) and forks every
    worker from itself, so workers start in milliseconds, share the imported code
    pages, and are never forked from a multi-threaded parent. Falls back to
    ``spawn`` where there is no fork server.
    """
    import multiprocessing as mp

    try:
        ctx = mp.get_context("forkserver")
    except ValueError:  # pragma: no cover - Windows
        return mp.get_context("spawn")
    from multiprocessing import forkserver

    ctx.set_forkserver_preload(list(_PRELOAD))
    with _env(THREAD_ENV):
        forkserver.ensure_running()
    return ctx


def prestart(kind: str = "processes") -> None:
    """Start the process pool's fork server now, so it imports the pipeline while
    this process gets on with its own imports (``vtcal batch`` calls it first)."""
    if kind == "processes":
        with contextlib.suppress(Exception):
            _process_context()


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
        (:func:`pipeline.cluster.preflight`)

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

        with ProcessPoolExecutor(max_workers=n, mp_context=_process_context()) as pool:
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
                from pipeline.cluster import preflight

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
                )
            )
            client = stack.enter_context(Client(cluster))
        yield client.get_executor(pure=False)


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
            from pipeline.artefacts import read_artefact

            self.summary_frame = read_artefact(self.summary_path, "batch_summary")
        return self.summary_frame

    @property
    def compare(self) -> Any:
        """The :class:`pipeline.compare.CompareResult` of the identified runs, or None."""
        if self.compare_result is None and self.reused and self.compare_lines:
            from pipeline.compare import compare_runs

            self.compare_result = compare_runs(_identified_runs(self.outcomes))
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
        if not _NAME_OK.match(n):
            raise BadInput(f"batch: run folder name {n!r} is not a plain folder name")


def _worker_failure(item: BatchItem, run_dir: Path, exc: BaseException) -> RecordingOutcome:
    """Outcome for a task whose worker did not return (died, not picklable, ...)."""
    return RecordingOutcome(
        name=item.name,
        recording=str(item.recording),
        run_dir=str(run_dir),
        robot=item.robot,
        notes=item.notes,
        status="error",
        error_kind="internal",
        error=_one_line(f"worker failed: {type(exc).__name__}: {exc}"),
        exit_code=70,
    )


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
        process is given ``grace_s`` to end, then terminated. Its recording is
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
    config : stage options for every recording (:class:`pipeline.orchestrator.RunConfig`)
    executor : an open executor to use (left open; every task is submitted to it at
        once); without it one is opened from ``kind``, ``workers``, ``scheduler``:
        for ``"processes"``, ``workers`` one-process pools fed one recording at a
        time, for ``"dask"`` :func:`open_executor`
    until, force : passed to every :func:`~pipeline.orchestrator.run_pipeline`
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
    :class:`pipeline.compare.CompareResult` (or None, ``compare_note`` says why). On
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
    _check_names(items)
    if until is not None:
        from pipeline.orchestrator import STAGES

        if until not in STAGES:
            raise BadInput(f"--until {until!r}: not a stage (stages: {', '.join(STAGES)})")
    if recycle_after < 0:
        raise BadInput(f"--recycle {recycle_after}: must be >= 0")
    if executor is None:
        _check_executor_options(kind, workers, scheduler)
    out_dir = Path(out).expanduser().absolute()
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    items = [
        BatchItem(it.name, Path(it.recording).expanduser().absolute(), it.robot, it.notes)
        for it in items
    ]
    outcomes: dict[str, RecordingOutcome] = {}
    interrupted = False
    timings: dict[str, float] = {}
    pending: list[BatchItem] = []
    try:
        for it in items:  # the run ledger, in this process: no worker for what is done
            rec = None if force else cached_outcome(it, out_dir / it.name, config, until)
            if rec is None:
                if not pending and executor is None:
                    prestart(kind)  # its imports overlap the remaining ledger checks
                pending.append(it)
                continue
            outcomes[it.name] = rec
            if progress is not None:
                progress(len(outcomes), len(items), rec)
        if pending:
            with contextlib.ExitStack() as stack:
                if executor is not None:
                    slots = [_Slot(executor, max(1, len(pending)))]
                elif kind == "processes":
                    ctx = _process_context()
                    n = min(workers or default_workers(), len(pending))

                    def make() -> Executor:
                        from concurrent.futures import ProcessPoolExecutor

                        return ProcessPoolExecutor(max_workers=1, mp_context=ctx)

                    slots = [_Slot(None, 1, make, recycle_after) for _ in range(n)]
                    for slot in slots:
                        stack.callback(slot.close)
                else:
                    ex = stack.enter_context(open_executor(kind, workers, scheduler, out_dir))
                    slots = [_Slot(ex, max(1, len(pending)))]
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
        interrupted = True
    timings["fan_out"] = time.perf_counter() - t0
    ordered = [
        outcomes.get(it.name)
        or RecordingOutcome(
            it.name,
            str(it.recording),
            str(out_dir / it.name),
            it.robot,
            it.notes,
            error="interrupted before it finished",
            error_kind="interrupted",
            exit_code=130,
        )
        for it in items
    ]
    fp = (
        None if interrupted else _batch_fingerprint(out_dir, items, ordered, config, until, compare)
    )
    path = out_dir / "summary.parquet"
    if not pending and fp is not None:
        kept = _reusable(out_dir, fp)
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
        _write_record(out_dir, fp, written, note, lines)
    seconds = time.perf_counter() - t0
    return BatchResult(out_dir, ordered, summary, path, seconds, False, cmp, note, timings, lines)


def _check_executor_options(kind: str, workers: int | None, scheduler: str | None) -> None:
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


# ---------------------------------------------------------------------------------------
# batch.json: the summary and comparison files of a batch, vouched for

#: file in the batch folder recording the fingerprint of the batch that wrote the
#: summary and comparison files, their hashes and the comparison's printed lines
BATCH_RECORD = "batch.json"


def _batch_fingerprint(
    out_dir: Path,
    items: Sequence[BatchItem],
    outcomes: Sequence[RecordingOutcome],
    config: RunConfig | None,
    until: str | None,
    compare: bool,
) -> dict[str, Any] | None:
    """What the summary and comparison depend on: the items, options, ``until`` and
    every run's ledger entry (recording, options, code, artefact hashes).

    None when a recording did not finish or its run folder has no ledger entry
    (such a batch is never taken as unchanged).
    """
    from pipeline import run_ledger
    from pipeline.fileio import config_hash
    from pipeline.orchestrator import RunConfig

    if any(o.status != "ok" for o in outcomes):
        return None
    runs = []
    for it in items:
        try:
            led = json.loads((out_dir / it.name / "run.json").read_text()).get(run_ledger.KEY)
        except (OSError, ValueError, AttributeError):
            return None
        if not isinstance(led, dict):
            return None
        runs.append(config_hash(led))
    return {
        "out": str(out_dir),
        "items": [[it.name, str(it.recording), it.robot, it.notes] for it in items],
        "config": run_ledger.config_json(config or RunConfig()),
        "until": until,
        "compare": compare,
        "runs": runs,
    }


def _reusable(out_dir: Path, fp: dict[str, Any]) -> dict[str, Any] | None:
    """``batch.json`` when it records ``fp`` and every file it lists is intact, else None."""
    from pipeline.fileio import file_hash

    try:
        rec = json.loads((out_dir / BATCH_RECORD).read_text())
        if not isinstance(rec, dict) or rec.get("fingerprint") != fp:
            return None
        files = rec["files"]
        if "summary.parquet" not in files:
            return None
        for name, want in files.items():
            if Path(name).name != name or file_hash(out_dir / name) != want:
                return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    return rec


def _write_record(
    out_dir: Path, fp: dict[str, Any], written: Sequence[Path], note: str, lines: Sequence[str]
) -> None:
    """Write ``batch.json`` (atomically, after the files it vouches for)."""
    from pipeline.fileio import atomic_write_bytes, file_hash

    rec = {
        "fingerprint": fp,
        "files": {p.name: file_hash(p) for p in written},
        "compare_note": note,
        "compare_lines": list(lines),
    }
    blob = json.dumps(rec, indent=1, sort_keys=True) + "\n"
    atomic_write_bytes(out_dir / BATCH_RECORD, blob.encode())


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
            finish(it, _worker_failure(it, out_dir / it.name, exc))

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
                    rec = _worker_failure(it, out_dir / it.name, exc)
                finish(it, rec)
    except BaseException:
        for fut in in_flight:
            fut.cancel()
        raise


# ---------------------------------------------------------------------------------------
# the summary


def _summary_columns() -> tuple[list[str], list[str]]:
    """Columns of the summary and the nullable ones, from ``schemas/batch_summary.json``."""
    from pipeline.artefacts import load_schema

    schema = load_schema("batch_summary")
    return schema.column_names, [c.name for c in schema.columns if c.nullable]


def summary_table(outcomes: Sequence[RecordingOutcome]) -> pd.DataFrame:
    """One row per recording, columns of ``schemas/batch_summary.json``."""
    import pandas as pd

    rows = []
    for o in outcomes:
        f = o.figures
        rows.append(
            {
                "name": o.name,
                "recording": o.recording,
                "run_dir": o.run_dir,
                "robot": o.robot or o.robot_urdf,
                "robot_urdf": o.robot_urdf,
                "notes": o.notes,
                "status": o.status,
                "error_kind": o.error_kind,
                "error": o.error,
                "exit_code": int(o.exit_code),
                "stages": " ".join(f"{s}:{st}" for s, st, _ in o.stages),
                "stages_ran": sum(st == "ran" for _, st, _ in o.stages),
                "stages_cached": sum(st == "cached" for _, st, _ in o.stages),
                "seconds": float(o.seconds),
                "cpu_seconds": float(o.cpu_seconds),
                "peak_rss_mb": o.peak_rss_mb,
                "worker": o.worker,
                "model": f.get("model"),
                "n_touchups": f.get("n_rows"),
                "n_used": f.get("n_used"),
                "n_targets": f.get("n_targets"),
                "n_identified": f.get("n_identified"),
                "n_params": f.get("n_params"),
                "rms_mm": f.get("rms_mm"),
                "max_mm": f.get("max_mm"),
                "predicted_shape_rms_mm": f.get("predicted_shape_rms_mm"),
                "predicted_absolute_rms_mm": f.get("predicted_absolute_rms_mm"),
                "cond": f.get("cond"),
                "scale_identified": f.get("scale_identified"),
                "headline": " | ".join(o.headline),
                "retried": bool(o.retried),
            }
        )
    columns, nullable = _summary_columns()
    df = pd.DataFrame(rows, columns=columns)
    for c in nullable:  # keep None (not NaN) so ints stay ints and bools stay bools
        df[c] = pd.Series([r[c] for r in rows], dtype=object)
    return df


def write_summary(
    out_dir: Path,
    summary: pd.DataFrame,
    *,
    config: RunConfig | None = None,
    until: str | None = None,
    force: bool = False,
) -> Path:
    """Write ``out_dir/summary.parquet`` (schema ``batch_summary``); return its path."""
    from pipeline.artefacts import write_artefact
    from pipeline.orchestrator import jsonable

    path = out_dir / "summary.parquet"
    write_artefact(
        path,
        summary,
        "batch_summary",
        stage="batch",
        config={"until": until, "force": force, "run": jsonable(config)},
        inputs={},
        extra_meta={"recordings": json.dumps(list(summary["recording"]) if len(summary) else [])},
    )
    return path


def compare_batch(out_dir: Path, outcomes: Sequence[RecordingOutcome]) -> tuple[Any, str]:
    """The cross-run table (``vtcal compare``) of the identified runs of a batch.

    Writes ``out_dir/compare.parquet`` (schema ``compare``) and
    ``out_dir/compare.html`` as ``vtcal compare`` does, for the runs that finished
    with identify (ran or cached), in batch order (the first run of each robot is
    the drift baseline).

    Returns
    -------
    (CompareResult or None, note): None with the reason when there is nothing to
    compare or :mod:`pipeline.compare` is absent or fails (the batch summary stands
    alone; a comparison failure never fails the batch).
    """
    runs = _identified_runs(outcomes)
    if not runs:
        return None, "no identified run to compare"
    try:
        from pipeline.compare import compare_runs, render_html
    except ImportError:
        return None, "cross-run comparison not available (pipeline.compare missing)"
    from pipeline.artefacts import atomic_write_bytes, write_artefact

    try:
        res = compare_runs(runs)
        write_artefact(
            out_dir / "compare.parquet",
            res.table,
            "compare",
            stage="compare",
            config={"k_sigma": res.summary.get("k_sigma")},
            inputs={},
            extra_meta={"runs": ",".join(res.summary.get("runs", []))},
        )
        atomic_write_bytes(out_dir / "compare.html", render_html(res).encode())
    except VtcalError as exc:
        return None, f"comparison failed: {_one_line(str(exc))}"
    except Exception as exc:  # a bug there must not cost the batch its summary
        return None, f"comparison failed: internal error: {internal_error_line(exc)}"
    return res, f"{out_dir / 'compare.parquet'}, {out_dir / 'compare.html'}"


def _identified_runs(outcomes: Sequence[RecordingOutcome]) -> list[Path]:
    return [Path(o.run_dir) for o in outcomes if o.status == "ok" and o.figures]


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    return format(v, spec)


def compare_lines(res: Any) -> list[str]:
    """The printed lines of a :class:`pipeline.compare.CompareResult`: the shipped
    model's line per run, the verdict and the drift flags (every model is in compare.html).

    Stored in ``batch.json`` so that an unchanged batch prints them without
    rebuilding the comparison.
    """
    lines = ["cross-run comparison (vtcal compare), shipped model:"]
    for r in res.runs.itertuples():
        if not r.shipped:
            continue
        lines.append(
            f"  {r.run:<20} {r.model:<8} held-out {_fmt(r.heldout_rms_mm, '.4f')} mm  "
            f"training {_fmt(r.train_rms_mm, '.4f')} mm  cond {_fmt(r.cond, '.3g')}  "
            f"rejected {r.n_rejected}"
        )
    lines.append(f"  {res.summary.get('verdict', '')}")
    moved = res.moved
    if len(moved):
        shipped = {(r.run, r.model) for r in res.runs.itertuples() if r.shipped}
        for (run, model), g in moved.groupby(["run", "model"], sort=False):
            if (run, model) not in shipped:
                continue
            top = g.reindex(g["delta_sigma"].abs().sort_values(ascending=False).index)
            names = ", ".join(str(p) for p in top["parameter"].head(3))
            lines.append(
                f"    {run} [{model}] against {g['baseline_run'].iloc[0]}: {len(g)} parameter(s) "
                f"moved (largest: {names})"
            )
    return lines
