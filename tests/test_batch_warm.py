"""A batch worker starts warm: what a fresh process pays once is paid in the fork server.

``pipeline.batch.warm`` (the batch's fork-server preload, ``RUN_PRELOAD``) imports the
modules a run loads lazily and loads the detector's compiled code, so a worker forked
from the server has them before its first recording (``benchmarks/bench_fleet_images.py``
measured a new worker's first recording at 4.0-4.1 CPU s against 2.3-2.9 s for its later
ones). The audit's workers neither detect nor report: its fork server does not pay it.

A process has one fork server, started with the preload of whoever starts it first, so
each case runs in a fresh interpreter.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

#: in a fresh interpreter: a one-worker pool on the context named by argv[1], and what
#: its worker holds before it runs anything
PROBE = """
import json, sys
from concurrent.futures import ProcessPoolExecutor

def state():
    # what the worker held before this function ran: read before importing anything
    # (importing pipeline.batch.warm would warm the worker itself)
    held = set(sys.modules)
    from pipeline.stages.detect import _jit
    compiled = len(_jit.fine_stage.signatures)
    from pipeline.batch import warm
    missing = [m for m in warm.LAZY if m not in held]
    return "pipeline.batch.warm" in held, missing, compiled, warm.FAILED

if __name__ == "__main__":
    from pipeline.batch.executor import RUN_PRELOAD, process_context
    from pipeline.audit.engine import PRELOAD as AUDIT
    preload = {"batch": RUN_PRELOAD, "audit": AUDIT}[sys.argv[1]]
    with ProcessPoolExecutor(max_workers=1, mp_context=process_context(preload)) as pool:
        print(json.dumps(pool.submit(state).result(timeout=300)))
"""


def _worker_state(tmp_path: Path, who: str) -> list:
    probe = tmp_path / "probe.py"
    probe.write_text(PROBE)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(
        [sys.executable, str(probe), who], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.splitlines()[-1])


def test_the_batch_preloads_the_warm_up() -> None:
    from pipeline.batch.executor import PRELOAD, RUN_PRELOAD

    assert RUN_PRELOAD == ("pipeline.batch.warm",)
    assert "pipeline.batch.warm" not in PRELOAD  # shared with the audit's pool


def test_a_forked_batch_worker_has_the_lazy_modules_and_the_compiled_detector(
    tmp_path: Path,
) -> None:
    preloaded, missing, compiled, failed = _worker_state(tmp_path, "batch")
    assert preloaded and failed == [] and missing == []
    assert compiled >= 1  # loaded before the worker ran anything


def test_the_audits_workers_do_not_pay_the_runs_warm_up(tmp_path: Path) -> None:
    preloaded, _, compiled, _ = _worker_state(tmp_path, "audit")
    assert not preloaded and compiled == 0
