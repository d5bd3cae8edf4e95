"""The HTML pages' one way to render a template of ``reports/`` (report and validation).

Light on purpose (jinja2 only), so that ``vtcal validate`` renders its page
without loading what the run report needs (pandas, the run's artefacts).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jinja2

from pipeline.resources import TEMPLATE_DIR


def render_template(name: str, fmt: Callable[..., str], **context: Any) -> str:
    """Render ``reports/NAME`` with the ``fmt`` filter and the stylesheet inlined as ``css``.

    Autoescaped; an undefined name is an error, not an empty string.
    """
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["fmt"] = fmt
    css = (TEMPLATE_DIR / "report.css").read_text()
    return env.get_template(name).render(css=css, **context)
