"""The HTML section of ``vtcal validate`` (template ``reports/validate.html.j2``).

Self-contained: the report's stylesheet inlined, no scripts, no external request
(the Content-Security-Policy forbids them).
"""

from __future__ import annotations

from typing import Any

import jinja2

from pipeline import __version__, resources
from pipeline.verdict import IMPROVED_BELOW

#: the report's templates (``reports/``); not imported from report.html, which loads pandas and the report data
TEMPLATE_DIR = resources.TEMPLATE_DIR
TEMPLATE = "validate.html.j2"


def _fmt(x: Any, digits: int = 3) -> str:
    return "–" if x is None else f"{float(x):.{digits}f}"


def render_validation(result: dict[str, Any]) -> str:
    """The page of one validation (:func:`pipeline.validate.validate` plus the command's paths)."""
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["fmt"] = _fmt
    css = (TEMPLATE_DIR / "report.css").read_text()
    return env.get_template(TEMPLATE).render(
        css=css,
        r=result,
        v=result["verdict"],
        nominal=result["robots"][-1],
        calibrated_name=str(result.get("calibrated", "")).rsplit("/", 1)[-1],
        input_name=str(result.get("input", "")).rsplit("/", 1)[-1],
        version=__version__,
        improved_below=IMPROVED_BELOW,
    )
