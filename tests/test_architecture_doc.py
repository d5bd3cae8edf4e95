"""docs/architecture.md is checked against the code (issue 37): its stage table, its
package layers and the module sizes it quotes.

* the stage table lists every stage of ``catalog.STAGES`` in run order, then the
  runner, each row naming every file its stage writes (the catalog's ``ARTEFACTS``);
* the package layers name every package of ``pipeline/``, each importing (directly or
  through top-level modules, lazy imports included) only packages before it;
* the largest modules it quotes are the largest, with their line counts.
"""

from __future__ import annotations

import re
from pathlib import Path

from pipeline.io.run_folder import ARTEFACTS
from pipeline.run.catalog import STAGE_NAMES
from tests.test_import_graph import _package_sources, analyse, package_edges

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "architecture.md").read_text()


def _section(title: str) -> str:
    start = DOC.index(title)
    end = DOC.find("\n## ", start + 1)
    return DOC[start : end if end > 0 else len(DOC)]


def stage_rows(text: str) -> list[tuple[str, str]]:
    """``(stage, writes cell)`` of each row of the stage table in ``text``."""
    rows = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 4 and not set(cells[0]) <= {"-"}:
            rows.append((cells[0].split()[0], cells[3]))
    return rows[1:]  # the header


def test_the_stage_table_is_the_catalogs() -> None:
    rows = stage_rows(_section("## Stages, artefacts and their writers"))
    assert [name for name, _ in rows] == [*STAGE_NAMES, "(runner)"]
    writes = dict(rows)
    for art in ARTEFACTS:
        stage = "(runner)" if art.writer == "runner" else art.writer
        shown = art.file.replace("{model}", "MODEL")
        assert f"`{shown}`" in writes[stage], (art.key, stage)


def layers(text: str) -> list[str]:
    """The package names of the "Package layers" paragraph, bottom up."""
    para = text[text.index("Package layers, bottom up") :].split("\n\n")[0]
    return re.findall(r"`([a-z_]+)`", para.split(":", 1)[1].split("):", 1)[-1])


def _reachable(edges: dict[str, set[str]], start: str) -> set[str]:
    seen: set[str] = set()
    todo = [start]
    while todo:
        for b in edges.get(todo.pop(), ()):
            if b not in seen:
                seen.add(b)
                todo.append(b)
    return seen


def misplaced(order: list[str], edges: dict[str, set[str]]) -> list[str]:
    """One line per package of ``order`` that reaches a package listed at or after it."""
    out = []
    for i, name in enumerate(order):
        reach = {n.split(".")[-1] for n in _reachable(edges, f"pipeline.{name}") if "." in n}
        above = set(order[i:]) & reach
        if above:
            out.append(f"{name} imports {sorted(above)}, listed after it")
    return out


def test_the_package_layers_are_the_import_graphs() -> None:
    order = layers(DOC)
    packages = sorted(p.parent.name for p in (ROOT / "pipeline").glob("*/__init__.py"))
    assert sorted(order) == packages
    assert misplaced(order, package_edges(analyse(_package_sources())[0])) == []


def test_the_largest_modules_quoted_are_the_largest() -> None:
    quoted = re.search(r"Largest modules now \(lines[^)]*\):\s*(.*?)\.\n", DOC, re.S)
    assert quoted is not None
    pairs = re.findall(r"`([\w/]+\.py)` (\d+)", quoted.group(1))
    sizes = {
        p.relative_to(ROOT / "pipeline").as_posix(): len(p.read_text().splitlines())
        for p in (ROOT / "pipeline").rglob("*.py")
    }
    top = sorted(sizes.items(), key=lambda kv: (-kv[1], kv[0]))[: len(pairs)]
    assert [(m, int(n)) for m, n in pairs] == top


def test_the_checks_can_fail() -> None:
    table = "| stage | computes | reads | writes |\n|---|---|---|---|\n| ingest | a | b | `x` |\n"
    assert stage_rows(table) == [("ingest", "`x`")]
    text = "Package layers, bottom up: each imports only those before it (`t.py`):\n`b`, `a`.\n"
    assert layers(text) == ["b", "a"]
    edges = {"pipeline.a": {"pipeline.top"}, "pipeline.top": {"pipeline.b"}}
    assert misplaced(["b", "a"], edges) == []
    assert misplaced(["a", "b"], edges) == ["a imports ['b'], listed after it"]
