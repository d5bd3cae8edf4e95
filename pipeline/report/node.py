"""The report stage's node: the run folder's artefacts in, report.html and run.rrd out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph); the
report's two files are written by the HTML and Rerun writers themselves.
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
