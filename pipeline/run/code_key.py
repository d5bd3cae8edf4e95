"""The code part of a stage's cache key: a digest of what computes the stage.

A stage's outputs are fresh when they were made from the same inputs, the same
configuration *and the same code* (a changed stage must not answer
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

Stages and their entry points are declared once, in :data:`pipeline.run.catalog.STAGES`
(``Stage.code``; :data:`ENTRY_POINTS` is that column): functions, or
:class:`~pipeline.run.lazy.Ref` to them, loaded here when a stage is keyed; a
function's module (the root of its import closure) is its ``__module__``. The compiled code of the
stage's own function (``Stage.fn``, its node: ``node.py`` in the stage's package) is
hashed too, but not the import closure of its module (its imports are the stage's
entry points, keyed by ``Stage.code``). The digest
is what the runner (:mod:`pipeline.run.runner`) adds to each stage's
configuration hash (``config_hash`` in the Parquet metadata) and to the
report's key in ``run.json``; the run ledger's ``code`` digest
(:func:`pipeline.run.ledger.code_digest`) covers every file of the package, so
a file change also defeats the ledger's whole-run shortcut.

Parsing the import closures is the slow part (0.2 s over the stages after ingest);
each module's parse is kept in a user cache file (:func:`import_cache_path`) keyed
by the digest of its bytes, so only an edited module is parsed again.
"""

from __future__ import annotations

import ast
import hashlib
import json
import sys
import types
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

from pipeline.io import resources
from pipeline.io.fileio import atomic_write_bytes, hash_named_files
from pipeline.io.resources import user_cache_dir
from pipeline.run import catalog
from pipeline.run.catalog import STAGES
from pipeline.run.lazy import Ref, resolve

PACKAGE_DIR = Path(__file__).resolve().parents[1]  # pipeline/ (this module is in pipeline/run/)
SCHEMA_DIR = resources.SCHEMA_DIR

#: an entry point: a function, or a :class:`~pipeline.run.lazy.Ref` to one
Entry = Ref | Callable[..., Any]

#: stage -> entry points that compute it (``catalog.STAGES``)
ENTRY_POINTS: dict[str, tuple[Entry, ...]] = {s.name: s.code for s in STAGES}

#: packages whose ``__init__`` imports every module of the package at run time
DYNAMIC_PACKAGES = ("pipeline.models",)


@cache
def _module_path(name: str) -> Path | None:
    """The source file of ``pipeline`` module ``name`` (package -> its ``__init__``).

    Looked up once per process, as :func:`module_closure` is (every stage's closure
    asks for its modules, their parents and their imports: 360 lookups of two
    ``stat`` calls each for the outliers stage alone, 5 ms of a run).
    """
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


def _parse_imports(name: str, source: bytes) -> list[str]:
    """The ``pipeline.*`` names module ``name`` imports anywhere in ``source``, sorted.

    Absolute and relative, module-level and function-level; a ``from pkg import x``
    also names ``pkg.x`` (it may be a module). Whether a name is a module is
    decided by the caller (files come and go; the parse of a source does not).
    """
    package = name if _is_package(name) else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
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
    return sorted(m for m in found if m.split(".")[0] == "pipeline")


#: parsed import lists by source digest, shared by every run of this user (see _imports)
_STORE: dict[str, list[str]] | None = None
_STORE_NEW: set[str] = set()  # keys parsed by this process, not yet written
_USED: set[str] = set()  # keys this process looked up
_STORE_FORMAT = 1
#: the cache file is rewritten without the entries this process did not use above this size
_STORE_MAX = 4000


def import_cache_path() -> Path:
    """``$XDG_CACHE_HOME/vtcal/code_key/imports.json``: parsed import lists by source digest."""
    return user_cache_dir("code_key") / "imports.json"


def _store() -> dict[str, list[str]]:
    global _STORE
    if _STORE is None:
        _STORE = {}
        try:
            data = json.loads(import_cache_path().read_text(encoding="utf-8"))
            if isinstance(data, dict) and data.get("format") == _STORE_FORMAT:
                entries = data.get("entries")
                if isinstance(entries, dict):
                    _STORE = entries
        except (OSError, ValueError):  # none yet, unreadable or damaged: parse again
            pass
    return _STORE


def _import_key(name: str, source: bytes) -> str:
    """Cache key of a module's parse: its name (relative imports), its bytes, the Python."""
    h = hashlib.sha256(f"{sys.version_info[0]}.{sys.version_info[1]}|{name}|".encode())
    h.update(source)
    return h.hexdigest()[:32]


def save_import_cache() -> None:
    """Write the parses this process added to :func:`import_cache_path` (never fails a run)."""
    if not _STORE_NEW or _STORE is None:
        return
    entries = _STORE
    if len(entries) > _STORE_MAX:
        entries = {k: v for k, v in entries.items() if k in _USED}
    try:
        path = import_cache_path()
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        text = json.dumps({"format": _STORE_FORMAT, "entries": entries}, sort_keys=True)
        atomic_write_bytes(path, text.encode("utf-8"))
        _STORE_NEW.clear()
    except OSError:  # read-only or full disk: parsed again next time
        pass


@cache
def _imports(name: str) -> frozenset[str]:
    """``pipeline`` modules that module ``name`` imports anywhere in its source.

    Parsed once per process (the stages' closures share most modules) and, across
    processes, once per source text: :func:`_parse_imports` of each module is kept
    in a user cache file keyed by the digest of the module's name and bytes and the
    Python version, so an edited module is parsed afresh and an unchanged one is
    not (parsing cost 0.2 s of every run after ingest). A missing or damaged cache
    only means parsing.
    """
    path = _module_path(name)
    if path is None:
        return frozenset()
    source = path.read_bytes()
    key = _import_key(name, source)
    store = _store()
    raw = store.get(key)
    if not (isinstance(raw, list) and all(isinstance(m, str) for m in raw)):
        raw = store[key] = _parse_imports(name, source)
        _STORE_NEW.add(key)
    _USED.add(key)
    return frozenset(m for m in raw if _module_path(m) is not None)


@cache
def module_closure(name: str) -> tuple[str, ...]:
    """Every ``pipeline`` module that importing (and running) ``name`` can execute, sorted.

    Parameters
    ----------
    name : dotted module name, e.g. ``"pipeline.stages.identify.stage"``

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
    stage : a stage of :data:`pipeline.run.catalog.STAGE` (read at the call: a registered one too)

    Returns
    -------
    str : 16 hex digits of SHA-256 over the sources of the entry modules' import
        closure, the schemas, and the entry functions' current code objects
    """
    h = hashlib.sha256()
    declared = catalog.STAGE[stage]  # read now: a registered stage is keyed too
    h.update(declared.fn_name.encode() + b"\0" + _code_bytes(declared.fn.__code__))
    _hash_entries(h, declared.code)
    save_import_cache()
    return h.hexdigest()[:16]


def _hash_entries(h: Any, entries: tuple[Entry, ...]) -> None:
    """Feed ``h`` the entry points' current code and their import closure's sources
    (each function's module: its ``__module__``)."""
    modules: set[str] = set()
    for entry in entries:
        fn = resolve(entry)
        mod = fn.__module__
        modules.update(module_closure(mod))
        code = getattr(fn, "__code__", None)
        name = getattr(fn, "__qualname__", None) or str(entry).rpartition(":")[2]
        h.update(f"{mod}:{name}".encode() + b"\0")
        h.update(_code_bytes(code) if code is not None else repr(fn).encode())
    h.update(_sources_digest(tuple(sorted(modules))))


def code_digest(entries: tuple[Entry, ...]) -> str:
    """Digest of the code behind entry points that are not a stage
    (the audit's fits, :mod:`pipeline.audit.cache`): as :func:`stage_code_digest`, the
    entry functions' code and their modules' import closure with the schemas.

    Returns
    -------
    str : 16 hex digits
    """
    h = hashlib.sha256()
    _hash_entries(h, tuple(entries))
    save_import_cache()
    return h.hexdigest()[:16]
