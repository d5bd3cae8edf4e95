"""What a fresh worker would pay on its first recording, paid once in the fork server.

``vtcal batch``'s process pool forks its workers from one fork server
(:func:`pipeline.batch.executor.process_context`), and replaces a worker after a number
of recordings (``recycle_after``). Importing this module in the fork server (the batch
preloads :data:`pipeline.batch.executor.RUN_PRELOAD`; a local Dask cluster's workers
import it at their start) does there, once, what each new worker
otherwise did on its first recording: it imports the modules a run loads lazily (the
report's, the ledger's, the MCAP index reader's) and loads the detector's and the edge
fit's compiled code from numba's cache
(:func:`pipeline.stages.detect.precompile.compile_detector`, ~0.4 s), so every forked
worker starts with them in memory. Measured with ``benchmarks/bench_fleet_images.py``:
a new worker's first recording took 4.0-4.1 CPU s against 2.3-2.9 s for its later ones.

The Rerun SDK is not imported here: its native library may start threads, and a fork
server must stay single-threaded. A failure here only leaves the warming out (the
worker then loads what it needs as before).
"""

from __future__ import annotations

import importlib

#: modules a run imports lazily, besides those the fork server already preloads
LAZY = (
    "pipeline.io.artefacts",
    "pipeline.export.provenance",
    "pipeline.run.ledger",
    "pipeline.accuracy.verdict",
    "pipeline.io.mcap_index",
    "pipeline.stages.outliers.adequacy",
    "pipeline.stages.detect.saturation",
    "pipeline.report.data",
    "pipeline.report.diagnosis",
    "pipeline.report.figures",
    "pipeline.report.html",
    "pipeline.report.images",
    "pipeline.report.outputs",
    "pipeline.report.plots",
    "pipeline.report.templates",
    "pipeline.report.touchup_views",
)


def warm() -> list[str]:
    """Import :data:`LAZY` and load the compiled detector; the names that failed."""
    failed = []
    for name in LAZY:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - warming is an optimisation only
            failed.append(name)
    try:
        from pipeline.stages.detect.precompile import compile_detector

        compile_detector()
    except Exception:  # noqa: BLE001
        failed.append("compile_detector")
    return failed


FAILED = warm()
