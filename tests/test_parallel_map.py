"""parallel_map survives a child that dies mid-task (killed, out of memory, a crash).

Before the liveness check, the parent waited for ever on the dead child's results
(seen once in a local test run: a defunct worker and the parent in ``get()``).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator

import pytest

from pipeline.stages.parallel_map import parallel_map


@pytest.fixture
def alarm() -> Iterator[None]:
    """Fail instead of hanging: SIGALRM after 30 s raises in the waiting parent."""

    def _raise(*_: object) -> None:
        raise TimeoutError("parallel_map hung waiting for a dead child")

    old = signal.signal(signal.SIGALRM, _raise)
    signal.alarm(30)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_a_child_that_dies_mid_task_does_not_hang_the_map(alarm: None) -> None:
    parent = os.getpid()

    def task(t: int) -> int:
        if os.getpid() == parent and t == 0:
            time.sleep(0.5)  # the parent is busy with task 0: the child takes task 1
        if os.getpid() != parent and t == 1:
            os._exit(3)  # the child dies holding task 1
        return 10 * t

    t0 = time.perf_counter()
    assert parallel_map(task, [0, 1, 2, 3, 4], workers=2) == [0, 10, 20, 30, 40]
    assert time.perf_counter() - t0 < 10.0


def test_children_that_live_give_the_serial_maps_results(alarm: None) -> None:
    assert parallel_map(lambda t: t * t, list(range(9)), workers=2) == [t * t for t in range(9)]
