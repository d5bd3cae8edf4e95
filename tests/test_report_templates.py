"""The compiled-template cache: the same page cold, warm, damaged or without a cache folder."""

from __future__ import annotations

from pathlib import Path

import pytest
from jinja2.bccache import bc_magic

from pipeline.report import templates
from pipeline.report.templates import render_template, template_cache_dir

TEMPLATE = """<style>{{ css }}</style>
{% for row in rows %}
  <p>{{ row | fmt }}</p>
{% endfor %}
{{ title }}
"""


@pytest.fixture
def template_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A template folder of one small page (and the stylesheet every page inlines)."""
    folder = tmp_path / "reports"
    folder.mkdir()
    (folder / "page.html.j2").write_text(TEMPLATE)
    (folder / "report.css").write_text("p { margin: 0 }")
    monkeypatch.setattr(templates, "TEMPLATE_DIR", folder)
    return folder


def _page() -> str:
    return render_template("page.html.j2", lambda x: f"{x:.2f}", rows=[1, 2.5], title="<b>")


def test_cold_warm_damaged_and_no_cache_render_the_same(
    template_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert template_cache_dir() == tmp_path / "cache" / "vtcal" / "jinja2"
    cold = _page()
    assert cold == "<style>p { margin: 0 }</style>\n  <p>1.00</p>\n  <p>2.50</p>\n&lt;b&gt;"
    files = list(template_cache_dir().glob("*.cache"))
    assert len(files) == 1  # compiled once, kept
    assert _page() == cold  # warm: loaded from the cache
    (template_dir / "page.html.j2").write_text(TEMPLATE.replace("{{ title }}", "changed"))
    assert _page().endswith("changed")  # a changed template is compiled afresh
    (template_dir / "page.html.j2").write_text(TEMPLATE)
    for damaged in (b"not bytecode at all", bc_magic + b"\x80\x05not a pickle"):
        files[0].write_bytes(damaged)
        assert _page() == cold  # damaged: compiled again
    blocked = tmp_path / "file"
    blocked.write_text("a file where the cache folder would go")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocked))
    assert templates._bytecode_cache() is None
    assert _page() == cold  # no cache folder: compiled every time


def test_the_key_names_the_jinja2_version_and_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    cache = templates._BytecodeCache("/nonexistent")
    key = cache.get_cache_key("report.html.j2")
    monkeypatch.setitem(templates.ENV_OPTIONS, "trim_blocks", False)
    assert cache.get_cache_key("report.html.j2") != key
    monkeypatch.setattr(templates.jinja2, "__version__", "0.0")
    assert cache.get_cache_key("report.html.j2") != key
