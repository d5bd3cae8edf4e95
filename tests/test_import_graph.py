"""The package's import graph: no cycle, no private name taken from another module (issue 20).

Every ``import`` and ``from ... import`` in ``pipeline/`` counts, at module level
and inside functions (a lazy import hides a cycle from Python, not from a reader):
the graph of ``pipeline`` modules must be acyclic. A name starting with one
underscore belongs to its module; no other module imports it or reaches it as
``module._name``. Both checks read the sources (``ast``), so they also cover
modules no test imports. Negative controls feed each check a cycle and a private
import, so the test can fail.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "pipeline"


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for p in root.rglob("*.py"):
        parts = p.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


def _source_of(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def analyse(sources: dict[str, tuple[str, bool]]) -> tuple[dict[str, set[str]], list[str]]:
    """Import edges between the given modules, and the private names imported across them.

    Parameters
    ----------
    sources : module name -> (source text, is a package ``__init__``)

    Returns
    -------
    edges : module -> modules of ``sources`` it imports
    private : one ``"importer: module._name"`` line per private name taken from another module
    """
    edges: dict[str, set[str]] = {m: set() for m in sources}
    private: list[str] = []
    for mod, (text, is_pkg) in sources.items():
        bound: dict[str, str] = {}  # local name -> module it names
        tree = ast.parse(text)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name in sources:
                        edges[mod].add(a.name)
                        bound[a.asname or a.name] = a.name
            elif isinstance(node, ast.ImportFrom):
                src = _source_of(node, mod, is_pkg)
                for a in node.names:
                    full = f"{src}.{a.name}"
                    if full in sources:
                        edges[mod].add(full)
                        bound[a.asname or a.name] = full
                    elif src in sources:
                        edges[mod].add(src)
                        if _private(a.name) and src != mod:
                            private.append(f"{mod}: {src}.{a.name}")
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and bound.get(node.value.id, mod) != mod
                and _private(node.attr)
            ):
                private.append(f"{mod}: {bound[node.value.id]}.{node.attr}")
        edges[mod].discard(mod)
    return edges, sorted(set(private))


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per back edge a depth-first search meets (empty when acyclic)."""
    state: dict[str, int] = {}
    found: list[list[str]] = []

    def visit(u: str, stack: list[str]) -> None:
        state[u] = 1
        stack.append(u)
        for v in sorted(edges.get(u, ())):
            if state.get(v) == 1:
                found.append(stack[stack.index(v) :] + [v])
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [])
    return found


def _package_sources() -> dict[str, tuple[str, bool]]:
    return {m: (p.read_text(), p.name == "__init__.py") for m, p in _modules(PACKAGE).items()}


def test_the_package_has_no_import_cycle() -> None:
    edges, _ = analyse(_package_sources())
    assert len(edges) > 50
    assert cycles(edges) == []


def _collapsed(edges: dict[str, set[str]], node: Callable[[str], str]) -> dict[str, set[str]]:
    """The graph of ``edges`` with each module replaced by ``node(module)`` (no self-loops)."""
    out: dict[str, set[str]] = {}
    for a, bs in edges.items():
        out.setdefault(node(a), set()).update(node(b) for b in bs if node(b) != node(a))
    return out


def package_edges(edges: dict[str, set[str]]) -> dict[str, set[str]]:
    """The import graph between packages: ``pipeline.X`` for every module of subpackage ``X``,
    a top-level module ``pipeline.m`` as itself (issue 37)."""

    return _collapsed(edges, lambda m: ".".join(m.split(".")[:2]))


def test_no_package_import_cycle() -> None:
    """``pipeline.estimation`` does not reach up into ``pipeline.stages``, nor
    ``pipeline.live`` into ``pipeline.sim`` (which runs its loop): the packages form
    layers, lazy imports included."""
    edges, _ = analyse(_package_sources())
    pk = package_edges(edges)
    assert {"pipeline.measurement", "pipeline.stages", "pipeline.sim", "pipeline.live"} <= set(pk)
    assert cycles(pk) == []


def subpackage_edges(edges: dict[str, set[str]], packages: set[str]) -> dict[str, set[str]]:
    """The import graph between the innermost packages: every module is its own package's
    node (``pipeline.stages.identify.data`` -> ``pipeline.stages.identify``), a package's
    ``__init__`` the package itself, a top-level module (``pipeline.cli``) itself. Finer than :func:`package_edges`, which sees
    ``pipeline/stages/`` as one node and so missed ``image <-> detect`` and
    ``identify <-> trust``."""

    def node(m: str) -> str:
        parent = m.rsplit(".", 1)[0]
        return m if m in packages or "." not in parent else parent  # top-level: itself

    return _collapsed(edges, node)


def test_no_subpackage_import_cycle() -> None:
    """No two packages at any depth import each other, directly or round a loop (the
    response curve sits below detect, the estimators that need the detector above it;
    the input guardrails below identify)."""
    sources = _package_sources()
    edges, _ = analyse(sources)
    sub = subpackage_edges(edges, {m for m, (_, is_pkg) in sources.items() if is_pkg})
    assert {"pipeline.stages.detect", "pipeline.stages.response", "pipeline.stages.image"} <= set(
        sub
    )
    assert "pipeline.stages.response" in sub["pipeline.stages.detect"]
    assert cycles(sub) == []


def test_the_subpackage_check_can_fail() -> None:
    """Two sub-packages of one package importing each other: a cycle the package graph
    cannot see (one node), the sub-package graph does."""
    fake = {
        "pipeline": ("", True),
        "pipeline.s": ("", True),
        "pipeline.s.a": ("", True),
        "pipeline.s.a.x": ("from pipeline.s.b.y import f\n", False),
        "pipeline.s.b": ("", True),
        "pipeline.s.b.y": ("def f():\n    from pipeline.s.a.z import g\n", False),
        "pipeline.s.a.z": ("", False),
    }
    edges, _ = analyse(fake)
    assert cycles(edges) == [] and cycles(package_edges(edges)) == []
    sub = subpackage_edges(edges, {m for m, (_, is_pkg) in fake.items() if is_pkg})
    assert cycles(sub) == [["pipeline.s.a", "pipeline.s.b", "pipeline.s.a"]]


def test_the_package_check_can_fail() -> None:
    fake = {
        "pipeline": ("", True),
        "pipeline.a": ("", True),
        "pipeline.a.x": ("from pipeline.b.y import f\n", False),
        "pipeline.b": ("", True),
        "pipeline.b.y": ("def f():\n    from pipeline.a import z\n", False),
        "pipeline.a.z": ("", False),
    }
    edges, _ = analyse(fake)
    assert cycles(edges) == []  # no module cycle ...
    assert cycles(package_edges(edges)) == [
        ["pipeline.a", "pipeline.b", "pipeline.a"]
    ]  # ... a package one


def test_no_module_takes_another_modules_private_names() -> None:
    _, private = analyse(_package_sources())
    assert private == []


def test_the_checks_can_fail() -> None:
    fake = {
        "pipeline": ("", True),
        "pipeline.a": ("from pipeline.b import helper\n", False),
        "pipeline.b": ("def helper():\n    from pipeline import a\n", False),
        "pipeline.c": ("from pipeline.a import _hidden\nimport pipeline.b as b\nb._x\n", False),
    }
    edges, private = analyse(fake)
    assert cycles(edges) == [["pipeline.a", "pipeline.b", "pipeline.a"]]
    assert private == ["pipeline.c: pipeline.a._hidden", "pipeline.c: pipeline.b._x"]
