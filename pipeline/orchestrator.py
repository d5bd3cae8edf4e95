"""The run orchestrator: stages in order, their artefacts on disk, content-based caching.

This is the one place (with :mod:`pipeline.artefacts`) where a run touches the
disk. Each stage is a pure function called here; its output artefacts carry in
their Parquet metadata the hashes of the inputs they were made from, a hash of
the stage's configuration and the package version. A stage whose outputs exist
and whose recorded inputs, configuration and version all match is skipped
(``force=True`` re-runs everything).

Before any of that, the run ledger (:mod:`pipeline.run_ledger`) is asked whether
the run folder is already exactly what this request makes: same recording bytes,
options, ``until``, version and code, every artefact intact. Then the run returns
at once with every stage cached, without loading pandas, pyarrow or a stage
module. Importing this module is light too (no numeric library).

Stages, in order (``--until`` stops after the named one)::

    ingest     recording.mcap -> frames.parquet, detections.parquet, recording.json
    touchups   frames, detections -> touchups.parquet
    outliers   touchups -> inliers.parquet
    identify   inliers -> parameters.parquet, residuals.parquet, targets.parquet,
               calibrated.urdf, identify.json
    crossval   inliers -> crossval.parquet
    report     every artefact -> report.html, run.rrd
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline import __version__
from pipeline.catalog import run_paths
from pipeline.code_key import stage_code_digest
from pipeline.errors import BadInput, CalibrationFailed
from pipeline.fileio import atomic_write_bytes, config_hash, file_hash
from pipeline.known_distances import parse_distances
from pipeline.recording_layout import locate

STAGES = ("ingest", "touchups", "outliers", "identify", "crossval", "report")

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
class RunResult:
    """Everything the CLI prints at the end of a run."""

    out_dir: Path
    stages: list[StageRecord]
    summary: dict[str, Any]


def jsonable(obj: Any) -> Any:
    """JSON form of configs and summaries; numpy arrays (bulk data) are left out."""
    np = sys.modules.get("numpy")  # not loaded: nothing here can be a numpy value

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: jsonable(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            if np is None or not isinstance(getattr(obj, f.name), np.ndarray)
        }
    if np is not None and isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def json_bytes(obj: Any) -> bytes:
    """The bytes of a JSON side file (sorted keys, one-space indent: byte-stable)."""
    return (json.dumps(jsonable(obj), indent=1, sort_keys=True) + "\n").encode()


def write_json(path: Path, obj: Any) -> None:
    """Atomically write a JSON side file (:func:`json_bytes`)."""
    atomic_write_bytes(path, json_bytes(obj))


def is_fresh(outputs: list[Path], inputs: Mapping[str, str], config: Mapping[str, Any]) -> bool:
    """True when every output exists and its Parquet metadata records these inputs and config.

    Non-Parquet outputs only need to exist; they are written after the stage's
    Parquet artefacts, so their presence plus a fresh Parquet means the stage finished.
    """
    from pipeline.artefacts import read_meta

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


@dataclass
class RunConfig:
    """Options of ``vtcal run`` that change what the stages compute.

    ``overrides`` replace keys of the recording's ``touchup`` metadata
    (``base_link``, ``polarity``, ``known_distances``, ...). ``stage_options``
    holds per-stage keyword overrides for the stage config dataclasses
    (``{"identify": {"model": "full"}}``). ``tolerance_mm`` (``--tolerance-mm``) is
    written to ``run.json`` and judged in the report's verdict (PASS / FAIL).
    """

    image_topic: str | None = None
    joint_topic: str = "/joint_states"
    description_topic: str = "/robot_description"
    overrides: dict[str, str] = field(default_factory=dict)
    stage_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    report: bool = True
    tolerance_mm: float | None = None


def _build(cls: Any, options: Mapping[str, Any], **base: Any) -> Any:
    """Instantiate a stage config dataclass from defaults, ``base`` and user ``options``."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(options) - names
    if unknown:
        raise BadInput(f"unknown option(s) for {cls.__name__}: {', '.join(sorted(unknown))}")
    return cls(**{**{k: v for k, v in base.items() if k in names}, **dict(options)})


def _diameter(text: str | None) -> float | None:
    """The recording's printed target diameter (m), or None when absent or not a size."""
    try:
        d = float(text) if text else float("nan")
    except ValueError:
        return None
    return d if math.isfinite(d) and d > 0 else None


def _implied_diameter(touchups: Path) -> float | None:
    """The image-implied target diameter the touch-up stage recorded (None if absent)."""
    from pipeline.artefacts import read_meta

    try:
        value = float(read_meta(touchups).get("implied_target_diameter_m", "nan"))
    except (OSError, ValueError):
        return None
    return value if math.isfinite(value) else None


def run_pipeline(
    recording: Path,
    out: Path,
    config: RunConfig | None = None,
    *,
    until: str | None = None,
    force: bool = False,
    progress: Progress | None = None,
) -> RunResult:
    """Run every stage on one recording, writing artefacts into ``out``.

    Parameters
    ----------
    recording : MCAP file (``../shared/spec/recording.md``) or ROS bag (docs/ros-bags.md)
    out : run folder (created)
    config : stage options; defaults are the embedded defaults
    until : last stage to run (one of :data:`STAGES`)
    force : re-run stages even when their cached outputs are fresh
    progress : callback for progress bars

    Returns
    -------
    RunResult with one :class:`StageRecord` per stage and the identification summary.
    Without ``force``, a run folder the run ledger vouches for (see
    :func:`cached_run`) is returned as it stands, every stage ``cached``.
    """
    import time

    from pipeline import run_ledger

    cfg = config or RunConfig()
    if until is not None and until not in STAGES:
        raise BadInput(f"--until {until!r}: not a stage (stages: {', '.join(STAGES)})")
    last = STAGES.index(until) if until else len(STAGES) - 1
    recording = Path(recording)
    out = Path(out)
    locate(recording)  # a missing file, a directory that is not a bag: BadInput now
    parse_distances(cfg.overrides.get("known_distances", ""))  # before the long ingest
    fp = run_ledger.fingerprint(recording, cfg, until)
    if not force:
        hit = _from_ledger(out, fp)
        if hit is not None:
            return hit

    import pandas as pd

    from pipeline.artefacts import read_artefact, write_artefact
    from pipeline.stages import detect, identify, ingest, outliers, touchup

    out.mkdir(parents=True, exist_ok=True)
    # temporaries a killed run left behind (atomic writes, the .rrd's partial save): never
    # artefacts; a run folder has one run at a time, so they are stale
    for stale in run_ledger.temporaries(out):
        stale.unlink(missing_ok=True)
    P = run_paths(out)
    records: list[StageRecord] = []
    opts = cfg.stage_options

    def stage(name: str, outputs: list[Path], inputs: dict[str, str], conf: Any, fn: Any) -> None:
        conf_dict = {"stage": name, "config": jsonable(conf), "code": stage_code_digest(name)}
        t0 = time.perf_counter()
        if not force and is_fresh(outputs, inputs, conf_dict):
            records.append(StageRecord(name, "cached", [p.name for p in outputs]))
            return
        fn(conf_dict)
        records.append(
            StageRecord(name, "ran", [p.name for p in outputs], time.perf_counter() - t0)
        )

    # -- ingest + detection (one streaming pass over the recording) --------------
    ingest_cfg = _build(
        ingest.IngestConfig,
        opts.get("ingest", {}),
        image_topic=cfg.image_topic,
        joint_topic=cfg.joint_topic,
        description_topic=cfg.description_topic,
        overrides=dict(cfg.overrides),
    )
    detect_cfg = _build(detect.DetectConfig, opts.get("detect", {}))
    rec_inputs = {"recording": fp["recording"]}

    def do_ingest(conf: dict[str, Any]) -> None:
        def cb(done: int, total: int | None) -> None:
            if progress:
                progress("ingest", done, total)

        # a fresh install compiles the detector first (~10-20 s): never a silent wait
        from pipeline.stages.detect_compile import compile_detector

        slow: list[bool] = []

        def announce() -> None:
            slow.append(True)
            if progress:
                progress("compile", 0, None)

        compile_detector(detect_cfg, on_slow=announce)
        if slow and progress:
            progress("compile", 1, 1)

        frames, detections, info = ingest.ingest_recording(
            recording.resolve(), ingest_cfg, detect_cfg, progress=cb
        )
        joint_meta = {"joint_names": json.dumps(list(info.joint_names))}
        write_artefact(
            P["frames"],
            frames,
            "frames",
            stage="ingest",
            config=conf,
            inputs=rec_inputs,
            extra_meta=joint_meta,
        )
        write_artefact(
            P["detections"],
            detections,
            "detections",
            stage="ingest",
            config=conf,
            inputs=rec_inputs,
        )
        write_json(P["recording"], info)

    stage(
        "ingest",
        [P["frames"], P["detections"], P["recording"]],
        rec_inputs,
        {"ingest": ingest_cfg, "detect": detect_cfg},
        do_ingest,
    )
    if last < STAGES.index("touchups"):
        return _finish(out, P, records, fingerprint=fp)

    info = ingest.RecordingInfo(**json.loads(P["recording"].read_text()))
    parse_distances(info.metadata.get("known_distances", ""))  # bad values fail now, not late
    if info.implausible and not opts.get("identify", {}).get("accept_implausible", False):
        raise CalibrationFailed(
            f"{recording}: implausible input: "
            + "; ".join(info.implausible)
            + " (rerun with --accept-implausible if it is right)"
        )

    # -- touch-up extraction ---------------------------------------------------
    touchup_cfg = _build(touchup.TouchupConfig, opts.get("touchups", {}))
    tu_inputs = hashes({"frames": P["frames"], "detections": P["detections"]})

    def do_touchups(conf: dict[str, Any]) -> None:
        frames = read_artefact(P["frames"], "frames")
        detections = read_artefact(P["detections"], "detections")
        table = touchup.extract_touchups(frames, detections, info, touchup_cfg)
        implied = table.attrs.get("implied_target_diameter_m", float("nan"))
        write_artefact(
            P["touchups"],
            table,
            "touchups",
            stage="touchups",
            config=conf,
            inputs=tu_inputs,
            extra_meta={"implied_target_diameter_m": repr(float(implied))},
        )

    stage("touchups", [P["touchups"]], tu_inputs, touchup_cfg, do_touchups)
    if last < STAGES.index("outliers"):
        return _finish(out, P, records, fingerprint=fp)

    # -- outlier rejection -------------------------------------------------------
    out_cfg = _build(outliers.OutlierConfig, opts.get("outliers", {}))
    ol_inputs = hashes({"touchups": P["touchups"]})

    def do_outliers(conf: dict[str, Any]) -> None:
        table = read_artefact(P["touchups"], "touchups")
        flagged = outliers.flag_outliers(table, info, out_cfg)
        write_artefact(
            P["inliers"], flagged, "inliers", stage="outliers", config=conf, inputs=ol_inputs
        )

    stage("outliers", [P["inliers"]], ol_inputs, out_cfg, do_outliers)
    if last < STAGES.index("identify"):
        return _finish(out, P, records, fingerprint=fp)

    # -- identification ----------------------------------------------------------
    id_cfg = _build(
        identify.IdentifyConfig,
        opts.get("identify", {}),
        model="all",  # every model; cross-validation picks the one the run ships
        distances=parse_distances(info.metadata.get("known_distances", "")),
        strict_distances=False,  # a truncated recording may not reach every target
        target_diameter_m=_diameter(info.metadata.get("target_diameter_m")),
        implied_target_diameter_m=_implied_diameter(P["touchups"]),
    )
    id_inputs = hashes({"inliers": P["inliers"]})

    def do_identify(conf: dict[str, Any]) -> None:
        table = read_artefact(P["inliers"], "inliers")
        result = identify.identify(table, info.urdf, info.base_link, info.flange_link, id_cfg)
        identify.write_outputs(result, out, stage_config=conf, inputs=id_inputs)

    stage(
        "identify",
        [P["parameters"], P["residuals"], P["targets"], P["calibrated_urdf"], P["identify"]],
        id_inputs,
        id_cfg,
        do_identify,
    )
    source = _recording_source(recording, P["frames"], fp)
    stamp_provenance(out, source)
    if last < STAGES.index("crossval"):
        return _finish(out, P, records, fingerprint=fp)

    # -- cross-validation and the choice of error model -----------------------------
    from pipeline.stages import crossval

    cv_cfg = _build(crossval.CrossvalConfig, opts.get("crossval", {}))
    # identify.json is not an input: this stage adds its verdict to it
    cv_inputs = hashes({"inliers": P["inliers"], "parameters": P["parameters"]})

    def do_crossval(conf: dict[str, Any]) -> None:
        table = read_artefact(P["inliers"], "inliers")
        crossval_and_choose(
            out,
            table,
            info.urdf,
            info.base_link,
            info.flange_link,
            id_cfg,
            cv_cfg,
            stage_config=conf,
            inputs=cv_inputs,
        )

    stage("crossval", [P["crossval"]], cv_inputs, cv_cfg, do_crossval)
    stamp_provenance(out, source)  # now with the shipped model's held-out error
    if last < STAGES.index("report") or not cfg.report:
        return _finish(out, P, records, fingerprint=fp)

    # -- report.html and run.rrd, from the artefacts alone ------------------------
    report_inputs = hashes(
        {
            k: P[k]
            for k in (
                "recording",
                "touchups",
                "inliers",
                "parameters",
                "residuals",
                "targets",
                "crossval",
                "identify",
                "calibrated_urdf",
            )
        }
    )
    report_inputs["code"] = stage_code_digest("report")  # the report's code is an input too
    report_inputs["tolerance_mm"] = repr(cfg.tolerance_mm)  # the verdict it shows
    previous = json.loads(P["run"].read_text()) if P["run"].exists() else {}
    if (
        not force
        and P["report"].exists()
        and P["rrd"].exists()
        and previous.get("report_inputs") == report_inputs
        and previous.get("version") == __version__
    ):
        records.append(StageRecord("report", "cached", ["report.html", "run.rrd"]))
    else:
        t0 = time.perf_counter()  # the report's imports (rerun, pandas) are waited for too
        from pipeline.report.outputs import build_outputs

        # the report shows the stage table: give it this run's, not the previous one
        write_json(
            P["run"],
            {"version": __version__, "stages": records, "tolerance_mm": cfg.tolerance_mm},
        )
        build_outputs(out)
        records.append(
            StageRecord("report", "ran", ["report.html", "run.rrd"], time.perf_counter() - t0)
        )
    del pd
    return _finish(out, P, records, report_inputs, fingerprint=fp, tolerance_mm=cfg.tolerance_mm)


def crossval_and_choose(
    out: Path,
    table: Any,
    urdf: str,
    base_link: str,
    flange_link: str,
    identify_config: Any,
    crossval_config: Any,
    *,
    stage_config: Mapping[str, Any],
    inputs: Mapping[str, str],
) -> Any:
    """Cross-validate, write ``crossval.parquet`` and ship the model with the least held-out error.

    When several error models were identified (``calibrated_MODEL.urdf`` beside
    ``calibrated.urdf``), the one with the smallest held-out error becomes
    ``calibrated.urdf``; ``identify.json`` records the choice and says it was made
    on held-out, not training, error. Used by ``vtcal run`` and ``vtcal identify``.
    """
    from pipeline.artefacts import write_artefact
    from pipeline.stages import crossval, identify

    P = run_paths(out)
    summary = json.loads(P["identify"].read_text())
    models = summary.get("models")
    result = crossval.cross_validate(
        table,
        urdf,
        base_link,
        flange_link,
        identify_config,
        crossval_config,
        full_fits=models if isinstance(models, dict) else None,
    )
    write_artefact(
        P["crossval"],
        result.table,
        "crossval",
        stage="crossval",
        config=stage_config,
        inputs=inputs,
    )
    chosen = result.chosen_model
    choice = str(result.summary.get("choice") or "")
    fitted = summary.get("models") or {}
    if chosen and chosen not in fitted and len(fitted) == 1:
        # one model asked for by a rule ('auto'): ship under the model it fitted
        rule, chosen = chosen, next(iter(fitted))
        choice = choice.replace(f": {rule},", f": {rule} (which fitted {chosen}),", 1)
    candidate = out / f"calibrated_{chosen}.urdf"
    if chosen and chosen != summary.get("best_model") and candidate.exists():
        atomic_write_bytes(P["calibrated_urdf"], candidate.read_bytes())
    if chosen and chosen in (summary.get("models") or {}):
        # every top-level figure becomes the shipped model's (not the first-fitted one's)
        summary = identify.shipped_summary(summary["models"], chosen)
    summary["crossval"] = result.summary
    if choice:
        lines = [
            line
            for line in summary.get("headline", [])
            if not line.startswith("calibrated.urdf from model")
        ]
        if chosen:
            lines.append(f"calibrated.urdf from model {chosen}")
        summary["headline"] = [*lines, choice]
    write_json(P["identify"], summary)
    return result


def _recording_source(recording: Path, frames: Path, fp: Mapping[str, Any]) -> Any:
    """Provenance source of a run: the recording's name, hash, time and the run id."""
    import pyarrow.parquet as pq

    from pipeline.provenance import Source, recorded_utc

    stamps = pq.read_table(frames, columns=["stamp_ns"]).column("stamp_ns").to_pylist()
    return Source(
        kind="recording",
        name=recording.name,
        sha256=str(fp["recording"]),
        run_id=config_hash(dict(fp)),
        recorded_utc=recorded_utc(stamps),
    )


def stamp_provenance(out: Path, source: Any) -> None:
    """Write the provenance block into ``out/calibrated.urdf`` (:mod:`pipeline.provenance`).

    From ``identify.json`` as it stands (the shipped model, and its held-out error
    once cross-validated) and ``source`` (a :class:`pipeline.provenance.Source`).
    Idempotent: the file is rewritten only when its bytes change. Nothing to do
    when either file is missing.
    """
    from pipeline.provenance import provenance_lines, stamp_urdf

    P = run_paths(out)
    if not (P["calibrated_urdf"].is_file() and P["identify"].is_file()):
        return
    summary = json.loads(P["identify"].read_text())
    old = P["calibrated_urdf"].read_text()
    new = stamp_urdf(old, provenance_lines(summary, source, __version__))
    if new != old:
        atomic_write_bytes(P["calibrated_urdf"], new.encode())


def render_outputs(out: Path, tolerance_mm: float | None = None) -> None:
    """``report.html`` and ``run.rrd`` from the artefacts in ``out`` alone."""
    from pipeline.report.outputs import build_outputs

    build_outputs(out, tolerance_mm)


def _finish(
    out: Path,
    P: dict[str, Path],
    records: list[StageRecord],
    report_inputs: dict[str, str] | None = None,
    *,
    fingerprint: dict[str, Any] | None = None,
    tolerance_mm: float | None = None,
) -> RunResult:
    """Write ``run.json`` (what each stage did, and the run ledger's entry) and the result."""
    from pipeline import run_ledger

    summary: dict[str, Any] = {}
    if P["identify"].exists():
        summary = json.loads(P["identify"].read_text())
    run: dict[str, Any] = {
        "version": __version__,
        "stages": records,
        "report_inputs": report_inputs,
        "tolerance_mm": tolerance_mm,
    }
    if fingerprint is not None:
        run[run_ledger.KEY] = run_ledger.entry(
            out, fingerprint, [name for r in records for name in r.outputs]
        )
    write_json(P["run"], run)
    return RunResult(out, records, summary)


def _from_ledger(out: Path, fp: dict[str, Any]) -> RunResult | None:
    """The run as it stands in ``out`` when the run ledger vouches for ``fp``, else None.

    On a hit ``run.json`` is brought to what a run with every stage cached writes
    (statuses ``cached``; rewritten only when that changes its bytes).
    """
    from pipeline import run_ledger

    run = run_ledger.lookup(out, fp)
    if run is None:
        return None
    P = run_paths(out)
    try:
        records = [
            StageRecord(str(s["stage"]), "cached", [str(o) for o in s.get("outputs", [])])
            for s in run["stages"]
        ]
        summary: dict[str, Any] = {}
        if P["identify"].exists():
            summary = json.loads(P["identify"].read_text())
        now = {
            "version": __version__,
            "stages": records,
            "report_inputs": run.get("report_inputs"),
            "tolerance_mm": run.get("tolerance_mm"),
            run_ledger.KEY: run[run_ledger.KEY],
        }
        blob = json_bytes(now)
        if P["run"].read_bytes() != blob:
            atomic_write_bytes(P["run"], blob)
    except (OSError, ValueError, TypeError, AttributeError):
        return None  # an odd run.json: let the per-stage checks decide
    return RunResult(out, records, summary)


def cached_run(
    recording: Path, out: Path, config: RunConfig | None = None, *, until: str | None = None
) -> RunResult | None:
    """The run of ``recording`` into ``out`` if the run ledger vouches it is complete, else None.

    What :func:`run_pipeline` returns without ``force`` when nothing changed,
    without running anything else: no numeric library or stage module is
    imported. Never raises: an unusable recording or run folder is a miss (the
    real run then reports it).

    Parameters
    ----------
    recording : MCAP file
    out : run folder
    config : stage options, as given to :func:`run_pipeline`
    until : last stage, as given to :func:`run_pipeline`
    """
    from pipeline import run_ledger

    try:
        recording, out = Path(recording), Path(out)
        if (until is not None and until not in STAGES) or not recording.exists():
            return None
        fp = run_ledger.fingerprint(recording, config or RunConfig(), until)
        return _from_ledger(out, fp)
    except (OSError, ValueError, BadInput):
        return None
