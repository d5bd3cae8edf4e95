"""One recording of a batch: the task a worker runs (:func:`run_recording`) and its small,
picklable outcome (status, one-line error, stage statuses, headline figures, peak RSS).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.batch.executor import THREAD_ENV
from pipeline.batch.manifest import BatchItem
from pipeline.errors import BadInput, CalibrationFailed, VtcalError
from pipeline.io.run_folder import RUN_FILES

if TYPE_CHECKING:
    from pipeline.run.orchestrator import RunConfig

#: Headline figures copied from ``identify.json`` into the summary (same names there).
FIGURES_INT = ("n_rows", "n_used", "n_targets", "n_identified", "n_params")
FIGURES_FLOAT = (
    "rms_mm",
    "max_mm",
    "predicted_shape_rms_mm",
    "predicted_absolute_rms_mm",
    "cond",
)


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
    verdict: str = ""

    @property
    def state(self) -> str:
        """What the batch prints in its status column: the run's own verdict once it finished.

        ``ok`` only for a calibration that improved on the nominal robot (and met its
        tolerance when the recording gave one); else ``not improved`` or ``FAIL``, as
        ``vtcal run`` would say; ``error`` / ``not_run`` for a recording that did not finish.
        """
        if self.status != "ok":
            return self.status
        return {"FAIL": "FAIL", "not improved": "not improved"}.get(self.verdict, "ok")


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


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def internal_error_line(exc: BaseException) -> str:
    """``Type: message (file:line)`` of the innermost frame, as the CLI reports bugs."""
    where = exc.__traceback__
    while where is not None and where.tb_next is not None:
        where = where.tb_next
    loc = f" ({where.tb_frame.f_code.co_filename}:{where.tb_lineno})" if where else ""
    return one_line(f"{type(exc).__name__}: {exc}{loc}")


def worker_failure(item: BatchItem, run_dir: Path, exc: BaseException) -> RecordingOutcome:
    """Outcome for a task whose worker did not return (died, not picklable, ...)."""
    return _item_outcome(
        item,
        run_dir,
        status="error",
        error_kind="internal",
        error=one_line(f"worker failed: {type(exc).__name__}: {exc}"),
        exit_code=70,
    )


def interrupted_outcome(it: BatchItem, out_dir: Path) -> RecordingOutcome:
    """The outcome of a recording the batch was interrupted before it finished."""
    return _item_outcome(
        it,
        out_dir / it.name,
        error="interrupted before it finished",
        error_kind="interrupted",
        exit_code=130,
    )


def _error_kind(exc: VtcalError) -> str:
    if isinstance(exc, BadInput):
        return "bad_input"
    if isinstance(exc, CalibrationFailed):
        return "calibration_failed"
    return "error"


def _robot_from_urdf(run_dir: Path) -> str:
    """The ``<robot name=...>`` of the URDF the recording carried (from recording.json)."""
    try:
        urdf = json.loads((run_dir / RUN_FILES["recording"]).read_text()).get("urdf", "")
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
    config, until, force : passed to :func:`pipeline.run.orchestrator.run_pipeline`

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
        from pipeline.batch.manifest import ensure_recording
        from pipeline.run.orchestrator import run_pipeline

        ensure_recording(item)  # a manifest's demo recording, simulated first when missing
        result = run_pipeline(item.recording, out, config, until=until, force=force)
    except VtcalError as exc:
        rec.status, rec.error_kind = "error", _error_kind(exc)
        rec.error, rec.exit_code = one_line(str(exc)), exc.exit_code
    except (Exception, SystemExit) as exc:  # a bug in a stage: reported, the batch goes on
        rec.status, rec.error_kind = "error", "internal"
        rec.error, rec.exit_code = internal_error_line(exc), 70
    else:
        take_result(rec, result)
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
    (:func:`pipeline.run.orchestrator.cached_run`). ``worker`` and the memory figures
    are this process's.
    """
    from pipeline.run.orchestrator import cached_run

    out = Path(run_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    result = cached_run(item.recording, out, config, until=until)
    if result is None:
        return None
    rec = _new_outcome(item, out)
    take_result(rec, result)
    return _close_outcome(rec, out, t0, c0)


def _new_outcome(item: BatchItem, out: Path) -> RecordingOutcome:
    """An outcome of ``item`` made in this process (it names this process as the worker)."""
    return _item_outcome(item, out, worker=f"{socket.gethostname()}:{os.getpid()}")


def _item_outcome(item: BatchItem, run_dir: Path, **fields: Any) -> RecordingOutcome:
    """An outcome of ``item`` run into ``run_dir``: the item's name, recording, robot and
    notes, then ``fields``."""
    return RecordingOutcome(
        name=item.name,
        recording=str(item.recording),
        run_dir=str(run_dir),
        robot=item.robot,
        notes=item.notes,
        **fields,
    )


def take_result(rec: RecordingOutcome, result: Any) -> None:
    """Stage statuses and, when identify ran or was cached, the figures of ``identify.json``
    and the run's verdict (:func:`pipeline.accuracy.verdict.verdict`, the one ``vtcal run`` prints:
    the validated figure, improved or not, PASS / FAIL against the recording's
    ``tolerance_mm`` when it has one)."""
    from pipeline.accuracy.verdict import verdict
    from pipeline.run.catalog import IDENTIFY

    rec.status = "ok"
    rec.stages = [(s.stage, s.status, float(s.seconds)) for s in result.stages]
    if any(s.stage == IDENTIFY for s in result.stages):
        summ = result.summary
        rec.figures = {"model": summ.get("best_model") or summ.get("model")}
        rec.figures["scale_identified"] = (
            None if "scale_held" not in summ else not bool(summ["scale_held"])
        )
        for k in FIGURES_INT + FIGURES_FLOAT:
            v = summ.get(k)
            rec.figures[k] = v if isinstance(v, (int, float)) else None
        rec.headline = [str(h) for h in summ.get("headline", [])]
        v = verdict(summ, run_tolerance(Path(rec.run_dir))) or {}
        for k in ("validated_mm", "validated_how", "nominal_mm", "tolerance_mm"):
            rec.figures[k] = v.get(k)
        rec.figures["verdict_line"] = v.get("line", "")
        rec.verdict = verdict_word(v)
        if v.get("passed") is False:
            rec.exit_code = 3  # what `vtcal run` exits with on FAIL


def verdict_word(v: dict[str, Any]) -> str:
    """``PASS`` / ``FAIL`` with a tolerance, else ``improved`` / ``not improved`` ('' unknown)."""
    if v.get("passed") is not None:
        return "PASS" if v["passed"] else "FAIL"
    if v.get("improved") is None:
        return ""
    return "improved" if v["improved"] else "not improved"


def run_tolerance(run_dir: Path) -> float | None:
    """The tolerance a run is judged by: run.json's (``--tolerance-mm``), else the
    recording's ``tolerance_mm`` metadata key (recording.json), as ``vtcal run`` does."""
    from pipeline.accuracy.verdict import tolerance_from_metadata

    for name, key in ((RUN_FILES["run"], None), (RUN_FILES["recording"], "metadata")):
        try:
            data = json.loads((run_dir / name).read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(data, dict):
            continue
        t = tolerance_from_metadata(data if key is None else data.get(key))
        if t is not None:
            return t
    return None


def _close_outcome(rec: RecordingOutcome, out: Path, t0: float, c0: float) -> RecordingOutcome:
    rec.seconds = time.perf_counter() - t0
    rec.cpu_seconds = time.process_time() - c0
    rec.robot_urdf = _robot_from_urdf(out)
    rec.peak_rss_mb = peak_rss_mb()
    rec.rss_mb = rss_mb()
    return rec
