"""The report stage's node: the run folder's artefacts in, report.html and run.rrd out.

Called by the runner as declared in :data:`pipeline.run.catalog.STAGES`: the
artefacts the stage reads (``data``), its options and the run's context
(:class:`pipeline.run.runner.Context`) in, ``{artefact key: value}`` out for the
runner to write; nothing here writes a file (the report's two files are written by the HTML and Rerun writers themselves). The stage's computation is
imported inside the function, so importing this module stays cheap (the catalog
imports it) and a function replaced at run time is the one that runs (and the one
the stage code key hashes, :mod:`pipeline.run.code_key`).
"""

from __future__ import annotations

from typing import Any


def report(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """report.html and run.rrd from the run folder's artefacts alone (written by their writers)."""
    warm = getattr(context, "warm_report", None)
    built = warm.build(context.out, context.tolerance_mm) if warm is not None else None
    if built is None:  # no warm process (pipeline.report.warm), or it is gone
        from pipeline.report import outputs

        built = outputs.build_outputs(context.out, context.tolerance_mm)
    html, rrd = built
    return {"report": html, "rrd": rrd}
