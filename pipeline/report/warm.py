"""The report built by a process started early, on a core the solver stages leave idle.

What the report stage waits for is mostly not its own work: loading the Rerun
SDK (0.25-0.3 s of Python imports) and decompressing the recording's frames for
the touch-ups' last captures (0.05-0.2 s). Both can be done before the stage
starts: the SDK needs nothing of the run, the frames only the touch-ups table.

:class:`WarmReport` forks one process when ``vtcal run`` starts (the orchestrator),
which imports the SDK and the report's modules while this process ingests the
recording: ingest keeps one core busy (98 % CPU of one core over its wall time
on the UR5e-like cell), so the imports take the other. After the touch-ups stage
it is told to read the frames it will show (:meth:`WarmReport.prefetch`; until it
says it has, the fits count its core as busy and do not fork onto it: see
:func:`pipeline.stages.parallel_map.register_busy`); when
the report stage comes, it is handed the run folder, builds ``report.html`` and
``run.rrd`` from the artefacts as :func:`pipeline.report.outputs.build_outputs`
always does (the same files, written atomically), and sends back their paths or
the exception it met, which is raised here. The stage's seconds are still
measured around the whole of it; what moved is the waiting, onto a core that
was idle.

It is not started where it cannot help or must not run: with the environment
variable ``VTCAL_WARM_REPORT=0``, without ``fork``, in a
child process (a ``vtcal batch`` or Dask worker: the batch uses the cores), in a
daemonic process, or when the 1-minute load leaves no core free
(:func:`pipeline.stages.parallel_map.free_workers`). If the process dies or
cannot be reached, the report stage builds the outputs itself, as before.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.connection
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.stages import parallel_map


def can_start() -> bool:
    """True when a warm report process may be forked now (see the module docstring)."""
    return (
        os.environ.get("VTCAL_WARM_REPORT", "1") != "0"
        and "fork" in multiprocessing.get_all_start_methods()
        and multiprocessing.parent_process() is None
        and not multiprocessing.current_process().daemon
        and parallel_map.free_workers() >= 2
    )


class WarmReport:
    """A forked process that builds a run's report when asked (see the module docstring)."""

    def __init__(self, process: Any, conn: multiprocessing.connection.Connection) -> None:
        self._process = process
        self._conn: multiprocessing.connection.Connection | None = conn
        self._reading = False
        parallel_map.register_busy(self.cores_busy)

    def cores_busy(self) -> int:
        """1 while the process reads frames (:meth:`prefetch` until it says it is done),
        else 0: registered with :func:`pipeline.stages.parallel_map.register_busy`, so
        the fits started meanwhile do not fork onto the core it uses."""
        if self._reading and self._conn is not None:
            try:
                while self._reading and self._conn.poll(0):
                    self._note(self._conn.recv())
            except (EOFError, OSError):
                self._reading = False
        return 1 if self._reading and self._conn is not None else 0

    def _note(self, message: Any) -> Any:
        """``message`` unless it is the process's "frames read" notice (then None)."""
        if message == ("prefetched",):
            self._reading = False
            return None
        return message

    @classmethod
    def start(cls, code_digest: Callable[[], str] | None = None) -> WarmReport | None:
        """Fork the process, or None when :func:`can_start` says no or the fork fails.

        ``code_digest`` computes the report's code digest (the run's machinery hands it
        in: ``stage_code_digest("report")``, so the report does not import the stage
        table); the process calls it when asked (:meth:`code_digest`). Without it the
        process cannot say, and the caller computes the digest itself.
        """
        if not can_start():
            return None
        ctx = multiprocessing.get_context("fork")
        here, there = ctx.Pipe()
        proc = ctx.Process(
            target=_serve, args=(there, here, code_digest), name="vtcal-report", daemon=True
        )
        try:
            proc.start()
        except OSError:
            return None
        there.close()
        return cls(proc, here)

    def _send(self, message: Any) -> bool:
        if self._conn is None:
            return False
        try:
            self._conn.send(message)
            return True
        except (OSError, ValueError):  # the process is gone
            self.close()
            return False

    def _ask(self, message: Any) -> tuple[str, Any] | None:
        """Send ``message`` and wait for the reply ``(status, value)``; None when the
        process cannot be reached (it is then closed)."""
        if not self._send(message):
            return None
        assert self._conn is not None
        try:
            reply: tuple[str, Any] | None = None
            while reply is None:
                reply = self._note(self._conn.recv())
        except (EOFError, OSError):
            self.close()
            return None
        return reply

    def prefetch(self, run_dir: Path) -> None:
        """Have the frames of every touch-up's last capture read (touchups.parquet exists);
        the process counts as a busy core (:meth:`cores_busy`) until it has read them."""
        self._reading = self._send(("prefetch", str(run_dir)))

    def code_digest(self) -> str | None:
        """The report's code digest (the ``code_digest`` function :meth:`start` was handed:
        :func:`pipeline.run.code_key.stage_code_digest`) computed there, where the report's
        modules are loaded anyway; None when it cannot be asked or was handed none.

        The process is a fork of this one, made when the run started, and reads the same
        source files, so the digest is the one this process would compute; computing it
        here would import the report's modules only for it (0.07-0.12 s).
        """
        reply = self._ask(("digest",))
        return str(reply[1]) if reply is not None and reply[0] == "digest" else None

    def build(self, run_dir: Path, tolerance_mm: float | None) -> tuple[Path, Path] | None:
        """``(report.html, run.rrd)`` built by the process; None when it could not be asked.

        An exception the build raised there is raised here.
        """
        reply = self._ask(("build", str(run_dir), tolerance_mm))
        self.close()
        if reply is None:  # died while building: the caller builds
            return None
        if reply[0] == "error":
            raise reply[1]
        return Path(reply[1][0]), Path(reply[1][1])

    def close(self) -> None:
        """Stop the process (it exits when told or when the pipe closes); idempotent."""
        parallel_map.unregister_busy(self.cores_busy)
        self._reading = False
        if self._conn is not None:
            try:
                self._conn.send(None)
            except (OSError, ValueError):
                pass
            self._conn.close()
            self._conn = None
        self._process.join(timeout=5)
        if self._process.is_alive():  # pragma: no cover - stuck: do not wait for it
            self._process.terminate()
            self._process.join(timeout=5)


def _serve(
    conn: multiprocessing.connection.Connection,
    parent_end: multiprocessing.connection.Connection,
    code_digest: Callable[[], str] | None = None,
) -> None:
    """The process: load the SDK and the report's modules, then answer messages until told to stop."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle
    parent_end.close()

    import pipeline.report.rrd_log  # noqa: F401 - the Rerun SDK: what this process is for
    from pipeline.report.outputs import build_outputs, prefetch_frames

    frames: dict[int, Any] = {}
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        if message[0] == "digest":
            try:
                if code_digest is None:
                    raise RuntimeError("no code digest function was handed in")
                conn.send(("digest", code_digest()))
            except Exception as exc:  # noqa: BLE001 - the run computes it itself
                conn.send(("error", RuntimeError(str(exc))))
            continue
        if message[0] == "prefetch":
            try:
                frames = prefetch_frames(Path(message[1]))
            except Exception:  # noqa: BLE001 - only an optimisation: the build reads them
                frames = {}
            conn.send(("prefetched",))  # its core is free again (WarmReport.cores_busy)
            continue
        try:
            html, rrd = build_outputs(Path(message[1]), message[2], frames=frames)
            conn.send(("ok", (str(html), str(rrd))))
        except BaseException as exc:  # noqa: BLE001 - sent back and raised by the run
            try:
                conn.send(("error", exc))
            except Exception:  # noqa: BLE001 - an exception that does not pickle
                conn.send(("error", RuntimeError(f"report: {type(exc).__name__}: {exc}")))
        return
