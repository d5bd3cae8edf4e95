"""A batch worker starts warm: what a fresh process pays once is paid in the fork server.

``pipeline.batch.warm`` (in the fork server's preload) imports the modules a run loads
lazily and loads the detector's compiled code, so a worker forked from the server has
them before its first recording (``benchmarks/bench_fleet_images.py`` measured a new
worker's first recording at 4.0-4.1 CPU s against 2.3-2.9 s for its later ones).
"""

from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor

from pipeline.batch.executor import PRELOAD, process_context


def _state() -> tuple[bool, list[str], int, list[str]]:
    """In the worker, before it runs anything: whether the warm-up ran in its parent, the
    lazy modules missing, the detector's compiled signatures, what warming failed on."""
    preloaded = "pipeline.batch.warm" in sys.modules
    from pipeline.batch import warm
    from pipeline.stages.detect import _jit

    missing = [m for m in warm.LAZY if m not in sys.modules]
    return preloaded, missing, len(_jit.fine_stage.signatures), warm.FAILED


def test_the_fork_server_preloads_the_warm_up() -> None:
    assert PRELOAD[-1] == "pipeline.batch.warm"


def test_a_forked_worker_has_the_lazy_modules_and_the_compiled_detector() -> None:
    with ProcessPoolExecutor(max_workers=1, mp_context=process_context()) as pool:
        preloaded, missing, compiled, failed = pool.submit(_state).result(timeout=300)
    assert preloaded and failed == [] and missing == []
    assert compiled >= 1  # loaded before the worker ran anything
