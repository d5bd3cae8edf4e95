"""No stage name typed as a string outside the catalog (issue 47).

The stage names are written once, in :mod:`pipeline.run.catalog` (``INGEST``,
``TOUCHUPS``, ... and ``Stage.name``); code that names a stage uses those. The same
words are also artefact keys (``RUN_FILES["identify"]`` is ``identify.json``,
``data["touchups"]`` a node's input) and keys inside the files
(``identify.json["crossval"]``): those are the file format, not the stage, and stay.
So the scan flags a stage-name literal only where it names a stage:

* ``until=``, ``stage=``, ``name=``, ``follows=``, ``leave_out=``, ``uses_configs=``
  (the value, or an item of a tuple or list given there);
* a comparison with something called ``stage`` or ``name`` (``s.stage == "identify"``),
  or membership in, or the index in, a list of stage names (``"report" in names``,
  ``names.index("identify")``);
* a subscript, ``.get``, ``.setdefault`` or ``.pop`` on options or stage tables
  (a name holding ``config``, ``options``, ``after_stage`` or ``STAGE``);
* the stage argument of ``plan``, ``run_stages``, ``stage_code_digest``,
  ``stage_config`` and a progress callback (``progress("ingest", ...)``), also
  through ``partial``;
* a key of a dict of stage options (given as ``configs=``, to ``build_configs``, or
  assigned to a name holding ``config``, ``options`` or ``fixed``).

``pipeline/io/run_folder.py``'s file table names each file's writer (a stage) as
data: it sits below the catalog, which imports it, and ``tests/test_catalog.py``
checks each writer is a stage; none of its literals is in a position above.
"""

from __future__ import annotations

import ast
from pathlib import Path

from pipeline.run.catalog import STAGE_NAMES

ROOT = Path(__file__).resolve().parent.parent
CATALOG = ROOT / "pipeline" / "run" / "catalog.py"

NAMES = frozenset(STAGE_NAMES)
KEYWORDS = {"until", "stage", "name", "follows", "leave_out", "uses_configs"}
STAGE_CALLS = {"plan", "run_stages", "stage_code_digest", "stage_config", "progress"}
LISTS = {"names", "rest", "stage_names", "STAGE_NAMES", "planned"}
TABLE_HINTS = ("config", "options", "after_stage", "STAGE")
DICT_HINTS = ("config", "options", "fixed")


def _name(node: ast.AST) -> str:
    """The last name of ``a``, ``a.b``, ``a.b()`` ('' otherwise)."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Name):
        return node.id
    return ""


def _stage_literals(node: ast.AST | None) -> list[ast.Constant]:
    """``node`` if it is a stage-name literal, or the stage-name items of a tuple/list
    (either branch of ``a if c else b``)."""
    if isinstance(node, ast.IfExp):
        return _stage_literals(node.body) + _stage_literals(node.orelse)
    items = node.elts if isinstance(node, ast.Tuple | ast.List) else [node]
    return [c for c in items if isinstance(c, ast.Constant) and c.value in NAMES]


def _dict_keys(node: ast.AST | None) -> list[ast.Constant]:
    return _stage_literals(ast.Tuple(list(node.keys))) if isinstance(node, ast.Dict) else []  # type: ignore[arg-type]


def _table(node: ast.AST) -> bool:
    return any(h in _name(node) for h in TABLE_HINTS)


def flagged(source: str) -> list[tuple[int, str]]:
    """``(line, literal)`` of each stage-name literal of ``source`` that names a stage."""
    out: list[ast.Constant] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            for kw in node.keywords:
                if kw.arg in KEYWORDS:
                    out += _stage_literals(kw.value)
                if kw.arg == "configs":
                    out += _dict_keys(kw.value)
            fn = _name(node.func)
            if fn in STAGE_CALLS:
                out += [c for a in node.args for c in _stage_literals(a)]
            if fn == "partial" and node.args and _name(node.args[0]) in STAGE_CALLS:
                out += [c for a in node.args[1:] for c in _stage_literals(a)]
            if fn == "index" and isinstance(node.func, ast.Attribute) and node.args:
                out += _stage_literals(node.args[0]) if _name(node.func.value) in LISTS else []
            if fn == "build_configs":
                out += [c for a in node.args for c in _dict_keys(a)]
            if (
                fn in {"get", "setdefault", "pop"}
                and isinstance(node.func, ast.Attribute)
                and _table(node.func.value)
                and node.args
            ):
                out += _stage_literals(node.args[0])
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            for op, right in zip(node.ops, node.comparators, strict=True):
                left = sides[sides.index(right) - 1]
                if isinstance(op, ast.Eq | ast.NotEq):
                    for a, b in ((left, right), (right, left)):
                        if _name(b) in {"stage", "name"}:
                            out += _stage_literals(a)
                if isinstance(op, ast.In | ast.NotIn) and _name(right) in LISTS:
                    out += _stage_literals(left)
        elif isinstance(node, ast.Subscript) and _table(node.value):
            out += _stage_literals(node.slice)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(any(h in _name(t) for h in DICT_HINTS) for t in targets):
                out += _dict_keys(node.value)
    return sorted((c.lineno, str(c.value)) for c in out)


def test_no_stage_name_literal_outside_the_catalog() -> None:
    found = []
    for path in sorted((ROOT / "pipeline").rglob("*.py")):
        if path == CATALOG:
            continue
        for line, literal in flagged(path.read_text()):
            found.append(f"{path.relative_to(ROOT)}:{line}: {literal!r}")
    assert found == [], "name the stage by the catalog's constant (pipeline.run.catalog)"


def test_the_scan_can_fail() -> None:
    source = """
run_pipeline(rec, out, until="identify")
opts = context.configs["crossval"]
if s.stage == "report": pass
cfg.stage_options.get("identify", {})
stage_options.setdefault("ingest", {})
names = plan(None, leave_out=("report",))
if "choose" in names: pass
run_stages(["ingest"], ctx, names)
digest = partial(stage_code_digest, "report")
fixed = {"identify": {"model": "all"}}
progress("ingest", 1, 2)
names = plan(until, leave_out=() if report else ("report",))
names = names[names.index("identify") :]
"""
    assert [line for line, _ in flagged(source)] == [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14]
    file_format = """
path = run / RUN_FILES["identify"]
cv = summary.get("crossval") or {}
if "touchups" in data: tu = data["touchups"]
out = {"crossval": table}
"""
    assert flagged(file_format) == []
