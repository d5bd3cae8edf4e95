"""The HTML section of ``vtcal validate`` (template ``reports/validate.html.j2``).

Self-contained: the report's stylesheet inlined, no scripts, no external request
(the Content-Security-Policy forbids them).
"""

from __future__ import annotations

from typing import Any

from pipeline import __version__
from pipeline.accuracy.verdict import IMPROVED_BELOW
from pipeline.io.numfmt import fmt, short
from pipeline.report.templates import render_template

TEMPLATE = "validate.html.j2"


def render_validation(result: dict[str, Any]) -> str:
    """The page of one validation (:func:`pipeline.accuracy.validate.validate` plus the command's paths)."""
    return render_template(
        TEMPLATE,
        fmt,
        r=result,
        v=result["verdict"],
        nominal=result["robots"][-1],
        calibrated_name=str(result.get("calibrated", "")).rsplit("/", 1)[-1],
        input_name=str(result.get("input", "")).rsplit("/", 1)[-1],
        version=__version__,
        improved_below=IMPROVED_BELOW,
        tolerance=short(result["verdict"].get("tolerance_mm")),
    )
