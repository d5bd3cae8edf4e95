"""The code part of a stage's cache key: a digest of what computes the stage.

A stage's outputs are fresh when they were made from the same inputs, the same
configuration *and the same code* (issue 15: a changed stage must not answer
"cached" with its old artefacts). The code of a stage is

* the source of every ``pipeline`` module its entry points can import, found
  statically: the transitive closure of the ``pipeline.*`` imports
  (module-level and function-level, absolute and relative) of the entry
  modules, plus every package ``__init__`` on the way, plus every module of a
  package that imports its modules dynamically (:data:`DYNAMIC_PACKAGES`: the
  error-model registry);
* every file of ``schemas/`` (what the artefacts are checked against);
* the compiled code of the entry functions as they are bound *now* (bytecode,
  constants and names, recursively through nested functions), so a function
  replaced at run time (a plug-in, or a test's monkeypatch) changes the key
  even though no file changed.

Stages and their entry points are declared once, in :data:`pipeline.catalog.STAGES`
(``Stage.code``; :data:`ENTRY_POINTS` is that column). The compiled code of the
stage's own function (``Stage.fn``, in :mod:`pipeline.nodes`) is hashed too,
but not the import closure of its module (it imports every stage). The digest
is what the runner (:mod:`pipeline.runner`) adds to each stage's
configuration hash (``config_hash`` in the Parquet metadata) and to the
report's key in ``run.json``; the run ledger's ``code`` digest
(:func:`pipeline.run_ledger.code_digest`) covers every file of the package, so
a file change also defeats the ledger's whole-run shortcut.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import types
from functools import cache
from pathlib import Path

from pipeline import resources
from pipeline.catalog import STAGES
from pipeline.fileio import hash_named_files

PACKAGE_DIR = Path(__file__).resolve().parent
SCHEMA_DIR = resources.SCHEMA_DIR

#: stage -> ``module:function`` entry points that compute it (``catalog.STAGES``)
ENTRY_POINTS: dict[str, tuple[str, ...]] = {s.name: s.code for s in STAGES}

#: stage -> its function in :mod:`pipeline.nodes` (code object hashed, not its closure)
STAGE_FUNCTIONS: dict[str, str] = {s.name: s.fn for s in STAGES}

#: packages whose ``__init__`` imports every module of the package at run time
DYNAMIC_PACKAGES = ("pipeline.models",)


def _module_path(name: str) -> Path | None:
    """The source file of ``pipeline`` module ``name`` (package -> its ``__init__``)."""
    parts = name.split(".")
    if parts[0] != "pipeline":
        return None
    if len(parts) == 1:
        return PACKAGE_DIR / "__init__.py"
    rel = Path(*parts[1:])
    for cand in (PACKAGE_DIR / rel / "__init__.py", PACKAGE_DIR / rel.with_suffix(".py")):
        if cand.is_file():
            return cand
    return None


def _is_package(name: str) -> bool:
    path = _module_path(name)
    return path is not None and path.name == "__init__.py"


@cache
def _imports(name: str) -> frozenset[str]:
    """``pipeline`` modules that module ``name`` imports anywhere in its source.

    Parsed once per process: the stages' closures share most modules.
    """
    path = _module_path(name)
    if path is None:
        return frozenset()
    package = name if _is_package(name) else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_bytes())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import module`
    return frozenset(
        m for m in found if m.split(".")[0] == "pipeline" and _module_path(m) is not None
    )


@cache
def module_closure(name: str) -> tuple[str, ...]:
    """Every ``pipeline`` module that importing (and running) ``name`` can execute, sorted.

    Parameters
    ----------
    name : dotted module name, e.g. ``"pipeline.stages.identify"``

    Returns
    -------
    tuple of str : module names, ``name`` included, with their parent packages
    """
    seen: set[str] = set()
    todo = [name]
    while todo:
        mod = todo.pop()
        if mod in seen or _module_path(mod) is None:
            continue
        seen.add(mod)
        parts = mod.split(".")
        todo.extend(".".join(parts[:k]) for k in range(1, len(parts)))  # parent packages
        todo.extend(_imports(mod))
        if mod in DYNAMIC_PACKAGES:
            pkg_dir = _module_path(mod).parent  # type: ignore[union-attr]
            todo.extend(f"{mod}.{p.stem}" for p in pkg_dir.glob("*.py") if p.stem != "__init__")
    return tuple(sorted(seen))


def _code_bytes(code: types.CodeType) -> bytes:
    """A deterministic byte image of a code object: bytecode, names, constants (recursively)."""
    parts = [code.co_code, repr(code.co_names).encode(), repr(code.co_varnames).encode()]
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            parts.append(_code_bytes(const))
        elif isinstance(const, frozenset):
            parts.append(repr(sorted(map(repr, const))).encode())
        else:
            parts.append(repr(const).encode())
    return b"\0".join(parts)


def _source_path(mod: str) -> Path:
    """The source file of a module of an import closure (it exists: the closure checked)."""
    path = _module_path(mod)
    assert path is not None, mod
    return path


@cache
def _sources_digest(modules: tuple[str, ...]) -> bytes:
    h = hashlib.sha256()
    hash_named_files(h, ((mod, _source_path(mod)) for mod in modules))
    if SCHEMA_DIR.is_dir():
        schemas = sorted(q for q in SCHEMA_DIR.rglob("*") if q.is_file())
        hash_named_files(h, ((p.relative_to(SCHEMA_DIR).as_posix(), p) for p in schemas))
    return h.digest()


def stage_code_digest(stage: str) -> str:
    """Digest of the code that computes ``stage`` (see the module docstring).

    Parameters
    ----------
    stage : a key of :data:`ENTRY_POINTS`

    Returns
    -------
    str : 16 hex digits of SHA-256 over the sources of the entry modules' import
        closure, the schemas, and the entry functions' current code objects
    """
    h = hashlib.sha256()
    modules: set[str] = set()
    mod, attr = STAGE_FUNCTIONS[stage].split(":")
    node = getattr(importlib.import_module(mod), attr)
    h.update(STAGE_FUNCTIONS[stage].encode() + b"\0" + _code_bytes(node.__code__))
    for entry in ENTRY_POINTS[stage]:
        mod, attr = entry.split(":")
        modules.update(module_closure(mod))
        fn = getattr(importlib.import_module(mod), attr)
        code = getattr(fn, "__code__", None)
        h.update(entry.encode() + b"\0")
        h.update(_code_bytes(code) if code is not None else repr(fn).encode())
    h.update(_sources_digest(tuple(sorted(modules))))
    return h.hexdigest()[:16]
