"""The runner: walks ``catalog.STAGES``, skips fresh stages, and is the only writer.

For each stage of a plan the runner

1. hashes the files the stage reads (``Stage.inputs``; data handed in by the
   caller, :attr:`Context.given`, has no file and so no hash) and builds the
   stage's cache key: those hashes plus ``{"stage", "config", "code"}``
   (:func:`pipeline.run.code_key.stage_code_digest`);
2. skips the stage when its outputs are fresh (:func:`is_fresh`: every output
   exists and its Parquet metadata records these inputs and this key);
3. otherwise reads its inputs (lazily: a stage reads only what it asks for),
   calls ``Stage.fn(data, config, context)`` and writes what it returns, by the
   artefact's kind (:func:`write_output`): Parquet checked against its schema,
   JSON, text; Parquet first, so a JSON side file present means the stage finished.

How a stage is keyed is declared (``Stage.cache``), never looked up by its name.
``"always"`` (choose): cheap and without Parquet, it always runs, and a file is
rewritten only when its bytes change ("cached" when none did). ``"ledger"``
(report): keyed in ``run.json`` (``report_inputs``: the hashes of what it reads,
its code and the tolerance it judges with), its files written by their own
writers (HTML, Rerun). A stage that reads the recording itself (``Stage.source``,
ingest) is keyed by the recording's hash; a file per fitted model
(``Artefact.per_model``) is named by its index artefact's ``"models"`` list.

``vtcal run`` starts the runner at ingest (:func:`pipeline.run.orchestrator.run_pipeline`),
``vtcal identify`` at identify with the touch-up table given
(:mod:`pipeline.commands.identify`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline import __version__
from pipeline.errors import BadInput
from pipeline.io.fileio import atomic_write_bytes, config_hash, file_hash, write_group
from pipeline.io.jsonio import json_bytes, jsonable
from pipeline.io.run_folder import BY_KEY, Artefact, Parquet, run_paths
from pipeline.run.catalog import CHOOSE, IDENTIFY, STAGE, STAGE_NAMES, STAGES, Stage
from pipeline.run.code_key import stage_code_digest

#: Reports progress of a long stage: ``(stage, done, total or None)``.
Progress = Callable[[str, int, int | None], None]


@dataclass
class StageRecord:
    """What happened to one stage in a run."""

    stage: str
    status: str  # "ran", "cached", "skipped"
    outputs: list[str] = field(default_factory=list)
    seconds: float = 0.0
    note: str = ""


@dataclass
class Context:
    """What a run's stages know besides their input artefacts and options.

    Attributes
    ----------
    out : the run folder
    configs : ``{stage: options}`` of every stage of the plan (:func:`build_configs`)
    recording : the recording (ingest reads it), None when starting later
    recording_hash : its content hash (ingest's cache key)
    robot : ``(URDF text, base link, flange link)`` the fits use
    source : :class:`pipeline.export.provenance.Source` stamped into calibrated.urdf, or None
    tolerance_mm : the report's PASS/FAIL tolerance (None: run.json's, else the recording's)
    given : ``{artefact key: data}`` handed in instead of a file (``vtcal identify``'s table)
    force : rerun stages even when fresh
    ledger : write the stage table to ``run.json`` before the report (``vtcal run``)
    progress : progress callback
    records : what each stage did, in order (filled by :func:`run_stages`)
    warm_report : a :class:`pipeline.report.warm.WarmReport` the report stage hands
        its work to, or None
    after_stage : ``{stage: [callable(run folder), ...]}`` called in order once the stage
        has run or been found fresh (the warm report reads its frames after the
        touch-ups stage)
    written : ``{path: (file hash, Arrow table)}`` of the Parquet artefacts this run wrote:
        a later stage reading one takes the table instead of reading the file back while
        the file still has that hash (:func:`load_input`)
    stage : the name of the stage whose node is running (set by the runner before it
        calls the node: a node names its own stage, its progress and its option group
        by it, not by a string of its own)
    """

    out: Path
    configs: dict[str, Any] = field(default_factory=dict)
    recording: Path | None = None
    recording_hash: str | None = None
    robot: tuple[str, str, str] | None = None
    source: Any = None
    tolerance_mm: float | None = None
    given: dict[str, Any] = field(default_factory=dict)
    force: bool = False
    ledger: bool = False
    progress: Progress | None = None
    records: list[StageRecord] = field(default_factory=list)
    warm_report: Any = None
    after_stage: dict[str, list[Callable[[Path], None]]] = field(default_factory=dict)
    written: dict[Path, tuple[str, Any]] = field(default_factory=dict)
    stage: str = ""


def plan(until: str | None, *, leave_out: tuple[str, ...] = ()) -> list[str]:
    """The stages a run makes: every stage up to ``until``, and each stage declared to
    follow a planned one (``Stage.follows``: choose after identify), but ``leave_out``
    (the caller's switches: ``--no-report``, ``--no-crossval``).

    The shipped calibration (``calibrated.urdf``, ``identify.json``) is chosen
    whenever models were fitted: ``--until identify`` ships identify's training
    choice, ``--until crossval`` the held-out one.
    """
    unknown = [n for n in leave_out if n not in STAGE_NAMES]
    if unknown:
        raise ValueError(f"leave_out: {unknown} are not stages")
    if until is not None and until not in STAGE_NAMES:
        raise BadInput(f"--until {until!r}: not a stage (stages: {', '.join(STAGE_NAMES)})")
    names = list(STAGE_NAMES[: STAGE_NAMES.index(until) + 1] if until else STAGE_NAMES)
    for s in STAGES:  # a stage declared to follow a planned one runs with it
        if s.follows in names and s.name not in names:
            names.append(s.name)
    return [n for n in names if n not in leave_out]


def is_fresh(outputs: list[Path], inputs: Mapping[str, str], config: Mapping[str, Any]) -> bool:
    """True when every output exists and its Parquet metadata records these inputs and config.

    Non-Parquet outputs only need to exist (and a JSON one to parse); they are
    written after the stage's Parquet artefacts, so their presence plus a fresh
    Parquet means the stage finished.
    """
    from pipeline.io.artefacts import read_meta

    want_cfg = config_hash(config)
    parquet = [p for p in outputs if p.suffix == ".parquet"]
    if not all(p.exists() for p in outputs) or not parquet:
        return False
    for p in outputs:  # a damaged (hand-edited, copied half) JSON side file: redo the stage
        if p.suffix == ".json":
            try:
                json.loads(p.read_text())
            except (OSError, ValueError):
                return False
    for p in parquet:
        try:
            meta = read_meta(p)
        except Exception:
            return False
        if (
            meta.get("version") != __version__
            or meta.get("config_hash") != want_cfg
            or json.loads(meta.get("inputs", "{}")) != dict(inputs)
        ):
            return False
    return True


def hashes(paths: Mapping[str, Path]) -> dict[str, str]:
    """``{name: file hash}`` of existing input files."""
    missing = [str(p) for p in paths.values() if not p.exists()]
    if missing:
        raise BadInput(f"missing input artefact(s): {', '.join(missing)}")
    return {name: file_hash(p) for name, p in sorted(paths.items())}


def _model_names(art: Artefact, out: Path) -> list[str] | None:
    """The models a per-model artefact has files for, from its index artefact's ``"models"``
    (``models.json``; None when absent or unreadable)."""
    assert art.index is not None
    try:
        return list(json.loads(run_paths(out)[art.index].read_text())["models"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _per_model(art: Artefact, out: Path, models: Any) -> list[Path]:
    return [out / art.file.format(model=m) for m in models]


def output_paths(stage: Stage, out: Path) -> list[Path]:
    """The files ``stage`` writes into ``out`` (per-model files as their index names them)."""
    P = run_paths(out)
    paths: list[Path] = []
    for key in stage.outputs:
        art = BY_KEY[key]
        if art.per_model:
            names = _model_names(art, out)
            missing = [out / f"{P[str(art.index)].name}.missing"]
            paths += _per_model(art, out, names) if names else missing
        else:
            paths.append(P[key])
    return paths


def load_input(key: str, out: Path, written: Mapping[Path, tuple[str, Any]] | None = None) -> Any:
    """Artefact ``key`` of run folder ``out`` as a stage takes it.

    Parquet: a DataFrame (schema checked) with its ``vtcal.*`` metadata in
    ``attrs["vtcal"]``; JSON: a dict; the per-model URDFs: ``{model: text}``.
    ``written`` (:attr:`Context.written`): tables this run wrote, taken instead of
    reading the file back when the file's hash is still the one written (the file's
    bytes are that table: the same frame, without decoding and checking it again).
    """
    art = BY_KEY[key]
    if art.per_model:
        names = _model_names(art, out) or []
        return {m: p.read_text() for m, p in zip(names, _per_model(art, out, names), strict=True)}
    path = out / art.file
    if art.schema is not None:
        from pipeline.io.artefacts import read_artefact, read_meta, table_meta

        kept = (written or {}).get(path)
        if kept is not None and path.is_file() and file_hash(path) == kept[0]:
            frame = kept[1].to_pandas()
            frame.attrs["vtcal"] = table_meta(kept[1].schema)
            return frame
        table = read_artefact(path, art.schema)
        table.attrs["vtcal"] = read_meta(path)
        return table
    if path.suffix == ".json":
        return json.loads(path.read_text())
    return path.read_text()


class Inputs(Mapping[str, Any]):
    """A stage's input artefacts, read on first use (given data first)."""

    def __init__(self, keys: list[str], context: Context) -> None:
        self._keys = keys
        self._context = context
        self._cache: dict[str, Any] = {}

    def __getitem__(self, key: str) -> Any:
        if key not in self._keys:
            raise KeyError(key)
        if key not in self._cache:
            given = self._context.given
            self._cache[key] = (
                given[key]
                if key in given
                else load_input(key, self._context.out, self._context.written)
            )
        return self._cache[key]

    def __contains__(self, key: object) -> bool:
        return key in self._keys  # without reading it (Mapping's would)

    def meta(self, key: str) -> dict[str, str]:
        """The ``vtcal.*`` metadata of Parquet input ``key`` (its table's ``attrs["vtcal"]``),
        without reading its rows: a stage that needs only a figure its writer recorded
        (identify: the touch-ups' implied target size; choose: the capture noise and the
        cross-validation summary) does not read and check the whole table again."""
        if key not in self._keys:
            raise KeyError(key)
        table = self._cache.get(key, self._context.given.get(key))
        if table is not None:
            return dict(table.attrs.get("vtcal", {}))
        from pipeline.io.artefacts import read_meta

        return read_meta(self._context.out / BY_KEY[key].file)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


def write_output(
    key: str,
    value: Any,
    out: Path,
    *,
    stage: str,
    config: Mapping[str, Any],
    inputs: Any,
    written: dict[Path, tuple[str, Any]] | None = None,
) -> list[Path]:
    """Write one output of a stage by its artefact's kind; the paths written.

    Parquet (:class:`pipeline.io.run_folder.Parquet` or a DataFrame): checked against
    its schema, with the stage's key in the metadata (and, with ``written``, its hash and
    Arrow table kept there: :attr:`Context.written`). JSON: sorted keys
    (:func:`pipeline.io.jsonio.json_bytes`). URDF: text. Per-model URDFs: one file each. A path (the report's
    files): already written by its writer.
    """
    if isinstance(value, Path):
        return [value]
    art = BY_KEY[key]
    if art.per_model:
        paths = _per_model(art, out, value)
        for p, text in zip(paths, value.values(), strict=True):
            atomic_write_bytes(p, text.encode())
        return paths
    path = out / art.file
    if art.schema is not None:
        from pipeline.io.artefacts import write_artefact_table

        table = value if isinstance(value, Parquet) else Parquet(value)
        kept = write_artefact_table(
            path,
            table.data,
            art.schema,
            stage=stage,
            config=config,
            inputs=inputs,
            extra_meta=table.meta,
        )
        if written is not None:
            written[path] = kept
    elif path.suffix == ".json":
        atomic_write_bytes(path, json_bytes(value))
    else:
        atomic_write_bytes(path, str(value).encode())
    return [path]


def _write_changed(outputs: Mapping[str, Any], out: Path) -> bool:
    """Write the outputs of an always-computed stage whose bytes changed; True if any did."""
    changed = False
    with write_group():  # fsync-ed together, moved into place in this order
        for key, value in outputs.items():
            path = out / BY_KEY[key].file
            blob = json_bytes(value) if path.suffix == ".json" else value.encode()
            if not path.is_file() or path.read_bytes() != blob:
                atomic_write_bytes(path, blob)
                changed = True
    return changed


def input_hashes(stage: Stage, context: Context, names: list[str]) -> dict[str, str]:
    """The cache key's inputs: hashes of the files ``stage`` reads.

    Given data has no file, hence no hash; an artefact declared ``keyed=False``
    (``models.json``: its writer's Parquet outputs, read too, key its results)
    is left out.
    """
    if stage.source:
        return {"recording": str(context.recording_hash)}
    P = run_paths(context.out)
    keys = [k for k in stage.inputs if k in P and k not in context.given]
    keys += [k for k in stage.optional if BY_KEY[k].writer in names]
    return hashes({k: P[k] for k in keys if BY_KEY[k].keyed})


def build_options(cls: Any, options: Mapping[str, Any], **base: Any) -> Any:
    """Instantiate a stage config dataclass from defaults, ``base`` and user ``options``.

    A ``list[str]`` option given as text (``--set crossval.models=full,elastic``) is
    split at its commas.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(options) - set(fields)
    if unknown:
        raise BadInput(
            f"unknown option(s) for {cls.__name__}: {', '.join(sorted(unknown))} "
            f"(its options: {', '.join(sorted(fields))})"
        )
    given = {
        k: [x.strip() for x in v.split(",") if x.strip()]
        if isinstance(v, str) and str(fields[k].type) in ("list[str]", str(list[str]))
        else v
        for k, v in options.items()
    }
    return cls(**{**{k: v for k, v in base.items() if k in fields}, **given})


def build_configs(
    names: list[str],
    options: Mapping[str, Mapping[str, Any]],
    fixed: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """The options of stages ``names``, built in this one place from what the catalog
    declares (``Stage.config``, ``Stage.sub_configs``).

    Each option group's dataclass is built from its defaults, the run's ``fixed``
    values (``{group: {field: value}}``: what the caller knows, e.g. the recording's
    known distances) and the user's ``options`` (``--set GROUP.OPTION=VALUE``), by
    :func:`build_options`. A stage without a config is left out; one with sub-configs
    gets ``{group: options, ...}`` (ingest: ``ingest``, ``detect``).
    """
    fixed = fixed or {}
    out: dict[str, Any] = {}
    for name in names:
        stage = STAGE[name]
        if stage.config is None:
            continue
        groups = [(name, stage.config), *stage.sub_configs]
        built = {
            g: build_options(cls.load(), options.get(g, {}), **fixed.get(g, {}))
            for g, cls in groups
        }
        out[name] = built if stage.sub_configs else built[name]
    return out


def stage_config(name: str, context: Context) -> Any:
    """The options of stage ``name`` (:func:`build_configs`), None for a stage without."""
    return context.configs.get(name)


def _call(stage: Stage, context: Context, names: list[str]) -> dict[str, Any]:
    keys = [*stage.inputs, *(k for k in stage.optional if BY_KEY[k].writer in names)]
    # the options of the earlier stages it declares it takes (Stage.uses_configs)
    others = {other: context.configs[other] for other in stage.uses_configs}
    context.stage = stage.name
    result: dict[str, Any] = stage.fn(
        Inputs(keys, context), stage_config(stage.name, context), context, **others
    )
    return result


def report_key(stage: Stage, context: Context) -> dict[str, str]:
    """The report's cache key (kept in ``run.json``): its inputs' hashes, code, tolerance."""
    P = run_paths(context.out)
    key = hashes({k: P[k] for k in stage.inputs})
    warm = context.warm_report
    code = warm.code_digest() if warm is not None else None  # pipeline.report.warm
    key["code"] = code or stage_code_digest(stage.name)  # the report's code is an input too
    key["tolerance_mm"] = repr(context.tolerance_mm)  # the verdict it shows
    return key


def run_ledgered(stage: Stage, context: Context) -> dict[str, str] | None:
    """A stage keyed in ``run.json`` (``cache="ledger"``: the report; see the module
    docstring); its key in ``run.json`` mode, else None."""
    records = context.records
    outputs = [BY_KEY[k].file for k in stage.outputs]
    if not context.ledger:
        t0 = time.perf_counter()
        _call(stage, context, [])
        records.append(StageRecord(stage.name, "ran", outputs, time.perf_counter() - t0))
        return None
    t0 = time.perf_counter()  # the key's code digest and the report's imports are waited for too
    key = report_key(stage, context)
    P = run_paths(context.out)
    previous = json.loads(P["run"].read_text()) if P["run"].exists() else {}
    if (
        not context.force
        and all(P[k].exists() for k in stage.outputs)
        and previous.get("report_inputs") == key
        and previous.get("version") == __version__
    ):
        records.append(StageRecord(stage.name, "cached", outputs))
        return key
    # the report shows the stage table: give it this run's, not the previous one
    write_run(context.out, records, tolerance_mm=context.tolerance_mm)
    _call(stage, context, [])
    records.append(StageRecord(stage.name, "ran", outputs, time.perf_counter() - t0))
    return key


def write_run(
    out: Path, stages: list[StageRecord], *, changed_only: bool = False, **fields: Any
) -> None:
    """The one writer of ``run.json``: ``{"version", "stages", **fields}``, byte-stable
    (:func:`pipeline.io.jsonio.json_bytes`), atomic; with ``changed_only`` only when its bytes
    change. The runner writes this run's stage table before the report (which shows it),
    :mod:`pipeline.run.orchestrator` the finished run with its ledger entry."""
    path = run_paths(out)["run"]
    blob = json_bytes({"version": __version__, "stages": stages, **fields})
    if not changed_only or not path.is_file() or path.read_bytes() != blob:
        atomic_write_bytes(path, blob)


def run_stage(name: str, context: Context, names: list[str]) -> None:
    """Run (or find fresh) one stage of a plan ``names``; append its :class:`StageRecord`."""
    stage = STAGE[name]
    out = context.out
    t0 = time.perf_counter()
    if stage.cache == "always":
        changed = _write_changed(_call(stage, context, names), out)
        status = "ran" if changed or context.force else "cached"
        files = [p.name for p in output_paths(stage, out)]
        context.records.append(StageRecord(name, status, files, time.perf_counter() - t0))
        return
    conf = stage_config(name, context)
    key = {"stage": name, "config": jsonable(conf), "code": stage_code_digest(name)}
    inputs = input_hashes(stage, context, names)
    outputs = output_paths(stage, out)
    if not context.force and is_fresh(outputs, inputs, key):
        context.records.append(StageRecord(name, "cached", [p.name for p in outputs]))
        return
    result = _call(stage, context, names)
    # Parquet first, then the rest: a side file present means the stage finished
    order = sorted(stage.outputs, key=lambda k: BY_KEY[k].schema is None)  # stable: declared order
    written: list[Path] = []
    with write_group():  # fsync-ed together, moved into place in this order
        for k in order:
            written += write_output(
                k, result[k], out, stage=name, config=key, inputs=inputs, written=context.written
            )
    files = [p.name for p in output_paths(stage, out)]
    context.records.append(StageRecord(name, "ran", files, time.perf_counter() - t0))


def run_stages(names: list[str], context: Context, plan_names: list[str]) -> dict[str, str] | None:
    """Run stages ``names`` (a part of the plan ``plan_names``) in order.

    Returns the report's cache key when the report ran in ``run.json`` mode, else None.
    """
    context.out.mkdir(parents=True, exist_ok=True)
    key = None
    for name in names:
        if STAGE[name].cache == "ledger":
            key = run_ledgered(STAGE[name], context)
        else:
            run_stage(name, context, plan_names)
            for hook in context.after_stage.get(name, ()):
                hook(context.out)
    return key


def write_fits(results: Any, out: Path) -> dict[str, Path]:
    """Write identification results as the identify and choose stages would (library use).

    For a script or test that called :func:`pipeline.stages.identify.stage.identify`
    itself: the tables, ``models.json`` and per-model URDFs, then the training
    choice (no cross-validation, no provenance block) as ``calibrated.urdf``
    and ``identify.json``. Returns ``{artefact key: path}``.
    """
    from pipeline.stages.choose.stage import choose_model
    from pipeline.stages.identify.stage import fit_outputs

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fits = fit_outputs(results)
    paths: dict[str, Path] = {}
    for key in ("parameters", "residuals", "targets", "model_urdfs", "models"):
        written = write_output(key, fits[key], out, stage=IDENTIFY, config={}, inputs={})
        if key != "model_urdfs":
            paths[key] = written[0]
    urdf, summary = choose_model(fits["models"], fits["model_urdfs"], None)
    for key, value in (("calibrated_urdf", urdf), ("identify", summary)):
        paths[key] = write_output(key, value, out, stage=CHOOSE, config={}, inputs={})[0]
    return paths
