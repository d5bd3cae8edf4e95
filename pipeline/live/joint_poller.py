"""Joint states for the recording from a controller that only answers "where are you now".

The recording needs ``/joint_states`` at 50 Hz or more, while the arm moves and
while it is still (spec ``recording.md``). A controller that logs its own
samples serves them through ``JOINTLOG?`` (the simulated cell does: its clock is
simulated, so polling in wall time would sample nothing); for every other one
:class:`JointPoller` reads the joints in a background thread on a wall-time
grid and keeps what it read until the recorder drains it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from pipeline.live.protocols import JointReading, MeasureFault

#: default polling rate, Hz: twice the spec's minimum, so a late reply now and then
#: still leaves every 20 ms window with a sample
DEFAULT_RATE_HZ = 100.0


class JointPoller:
    """Call ``read`` every ``1/rate_hz`` s of wall time in a daemon thread.

    Parameters
    ----------
    read : callable returning a :class:`JointReading`
        Must be safe to call from another thread than the one that moves the
        robot (the TCP client gives it a connection of its own).
    rate_hz : float
        Polling rate; the grid is absolute (``t0 + k / rate``), so a slow reply
        delays one sample, not every later one.

    A fault in ``read`` stops the poller; :meth:`drain` then raises it, so the
    loop learns of a lost connection at its next recording step.
    """

    def __init__(self, read: Callable[[], JointReading], rate_hz: float = DEFAULT_RATE_HZ) -> None:
        self._read = read
        self._period = 1.0 / float(rate_hz)
        self._samples: list[JointReading] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._fault: MeasureFault | None = None
        self._thread = threading.Thread(target=self._run, name="vtcal-joint-poller", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set():
            try:
                r = self._read()
            except MeasureFault as exc:
                self._fault = exc
                return
            with self._lock:
                if not self._samples or r.stamp_ns > self._samples[-1].stamp_ns:
                    self._samples.append(r)
            k = max(k + 1, int((time.monotonic() - t0) / self._period))
            self._stop.wait(max(0.0, t0 + k * self._period - time.monotonic()))

    def drain(self) -> list[JointReading]:
        """The samples read since the last call, in stamp order."""
        with self._lock:
            out, self._samples = self._samples, []
        if not out and self._fault is not None:
            raise self._fault
        return out

    def stop(self) -> None:
        """Stop polling (returns once the thread has ended)."""
        self._stop.set()
        self._thread.join(timeout=2.0)
