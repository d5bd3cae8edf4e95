"""The HTML pages' one way to render a template of ``reports/`` (report and validation).

Light on purpose (jinja2 only), so that ``vtcal validate`` renders its page
without loading what the run report needs (pandas, the run's artefacts).

Compiling the report's template is most of a render (0.08 s of a 0.5 s report
stage): the compiled code is kept in a user cache folder
(:func:`template_cache_dir`) by jinja2's bytecode cache, keyed by the template,
its text, the jinja2 version and the environment's settings, so a changed
template, jinja2 or setting compiles afresh. Where no cache folder can be made,
templates are compiled every time, as before.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jinja2

from pipeline.io.resources import TEMPLATE_DIR, user_cache_dir

#: the settings of every template environment (part of the cache key)
ENV_OPTIONS: dict[str, Any] = {
    "autoescape": True,
    "undefined": jinja2.StrictUndefined,
    "trim_blocks": True,
    "lstrip_blocks": True,
}


def template_cache_dir() -> Path:
    """Where compiled templates are kept: ``$XDG_CACHE_HOME/vtcal/jinja2`` (``~/.cache``)."""
    return user_cache_dir("jinja2")


class _BytecodeCache(jinja2.FileSystemBytecodeCache):
    """jinja2's file cache, its key extended by the jinja2 version and :data:`ENV_OPTIONS`.

    jinja2's own key is the template's name and file name (the text is checked
    apart); compiled code also depends on the version and settings that made it.
    A cache file that does not read, or cannot be written, only means compiling:
    it never fails a render.
    """

    def get_cache_key(self, name: str, filename: str | None = None) -> str:
        env = repr(sorted((k, repr(v)) for k, v in ENV_OPTIONS.items()))
        key = f"{jinja2.__version__}|{env}|{name}|{filename}"
        return hashlib.sha1(key.encode("utf-8")).hexdigest()

    def load_bytecode(self, bucket: jinja2.bccache.Bucket) -> None:
        try:
            super().load_bytecode(bucket)
        except Exception:  # noqa: BLE001 - a damaged cache file: compile
            bucket.reset()

    def dump_bytecode(self, bucket: jinja2.bccache.Bucket) -> None:
        try:
            super().dump_bytecode(bucket)
        except OSError:  # full or read-only disk: compiled again next time
            pass


def _bytecode_cache() -> jinja2.BytecodeCache | None:
    """The cache in :func:`template_cache_dir`, None when the folder cannot be made."""
    folder = template_cache_dir()
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(folder, os.W_OK | os.X_OK):
        return None
    return _BytecodeCache(str(folder))


def render_template(name: str, fmt: Callable[..., str], **context: Any) -> str:
    """Render ``reports/NAME`` with the ``fmt`` filter and the stylesheet inlined as ``css``.

    Autoescaped; an undefined name is an error, not an empty string.
    """
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        bytecode_cache=_bytecode_cache(),
        **ENV_OPTIONS,
    )
    env.filters["fmt"] = fmt
    css = (TEMPLATE_DIR / "report.css").read_text()
    return env.get_template(name).render(css=css, **context)
