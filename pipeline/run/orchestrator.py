"""The run orchestrator: ``vtcal run`` as the runner started at ingest.

The pipeline is declared in :mod:`pipeline.run.catalog` (``STAGES``: each stage's
function, inputs, outputs and options; ``ARTEFACTS``: each file and its one
writer) and walked by :mod:`pipeline.run.runner`, the only writer of a run folder,
which skips a stage whose outputs are fresh (``force=True`` re-runs
everything). This module builds the stages' options from a :class:`RunConfig`
and the recording, checks the recording between ingest and the touch-ups, and
keeps the run ledger in ``run.json``.

Before any of that, the run ledger (:mod:`pipeline.run.ledger`) is asked whether
the run folder is already exactly what this request makes: same recording bytes,
options, ``until``, version and code, every artefact intact. Then the run returns
at once with every stage cached, without loading pandas, pyarrow or a stage
module. Importing this module is light too (no numeric library).

Stages, in order (``--until`` stops after the named one; ``choose`` follows
identify in every run that fits)::

    ingest     recording.mcap -> frames.parquet, detections.parquet, recording.json
    touchups   frames, detections, recording -> touchups.parquet
    outliers   touchups, recording -> inliers.parquet
    identify   inliers -> parameters.parquet, residuals.parquet, targets.parquet,
               calibrated_MODEL.urdf, models.json
    crossval   inliers, parameters, models -> crossval.parquet
    choose     models, calibrated_MODEL.urdf (, crossval) -> calibrated.urdf, identify.json
    report     every artefact -> report.html, run.rrd
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from pipeline.errors import BadInput, CalibrationFailed, VtcalError
from pipeline.io.fileio import config_hash
from pipeline.io.jsonio import json_bytes, jsonable, write_json
from pipeline.io.known_distances import metadata_distances
from pipeline.io.layout import locate
from pipeline.io.run_folder import RUN_FILES, run_paths
from pipeline.run import catalog
from pipeline.run.catalog import CHOOSE, IDENTIFY, INGEST, REPORT, STAGE_NAMES, TOUCHUPS
from pipeline.run.code_key import stage_code_digest
from pipeline.run.runner import (
    Context,
    Progress,
    StageRecord,
    build_configs,
    hashes,
    is_fresh,
    plan,
    run_stages,
    write_run,
)
from pipeline.run.withdraw import release, snapshot, withdraw

#: the stage names, in run order (``--until`` takes one)
STAGES = STAGE_NAMES

__all__ = [
    "STAGES",
    "Progress",
    "RunConfig",
    "RunResult",
    "StageRecord",
    "cached_run",
    "hashes",
    "is_fresh",
    "json_bytes",
    "jsonable",
    "run_paths",
    "run_pipeline",
    "write_json",
]


@dataclass
class RunResult:
    """Everything the CLI prints at the end of a run."""

    out_dir: Path
    stages: list[StageRecord]
    summary: dict[str, Any]


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


def _diameter(text: str | None) -> float | None:
    """The recording's printed target diameter (m), or None when absent or not a size."""
    try:
        d = float(text) if text else float("nan")
    except ValueError:
        return None
    return d if math.isfinite(d) and d > 0 else None


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
    recording : MCAP file (``spec/recording.md``) or ROS bag (docs/ros-bags.md)
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

    The run, in steps:

    1. check the request (``until``, the recording, known distances) and ask the run ledger;
    2. ingest (:func:`pipeline.run.runner.run_stages`);
    3. read recording.json, refuse an implausible recording, build the options of
       the later stages from it (:func:`stage_configs`);
    4. the rest of the plan (:func:`pipeline.run.runner.plan`), then ``run.json``.
    """
    from pipeline.run import ledger as run_ledger

    cfg = config or RunConfig()
    names = plan(until, leave_out=() if cfg.report else (REPORT,))
    recording = Path(recording)
    out = Path(out)
    locate(recording)  # a missing file, a directory that is not a bag: BadInput now
    metadata_distances(cfg.overrides)  # bad values fail before the long ingest
    fp = run_ledger.fingerprint(recording, cfg, until)
    if not force:
        hit = _from_ledger(out, fp)
        if hit is not None:
            return hit

    created = _first_missing(out)  # the folder this run makes (with any parent it makes)
    before = snapshot(out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _run_in(out, recording, cfg, names, fp, force, progress, before)
    except BaseException:
        if created is not None:  # a run that wrote nothing leaves no empty folder behind
            _remove_if_empty(created)
        raise
    finally:  # the previous files' links (a refusal has put them back already)
        release(out)


def _first_missing(folder: Path) -> Path | None:
    """The outermost of ``folder`` and its parents that does not exist (None: it exists):
    what ``folder.mkdir(parents=True)`` creates."""
    missing = None
    for p in (folder, *folder.parents):
        if p.exists():
            break
        missing = p
    return missing


def _remove_if_empty(folder: Path) -> None:
    """Remove ``folder`` (and its empty subfolders) when it holds no file."""
    import shutil

    try:
        if not any(p.is_file() for p in folder.rglob("*")):
            shutil.rmtree(folder)
    except OSError:
        pass


def _run_in(
    out: Path,
    recording: Path,
    cfg: RunConfig,
    names: list[str],
    fp: dict[str, Any],
    force: bool,
    progress: Progress | None,
    before: Any,
) -> RunResult:
    """Steps 2-4 of :func:`run_pipeline` in the run folder ``out`` (made); ``before`` its
    files when the run started (:func:`pipeline.run.withdraw.snapshot`)."""
    from pipeline.run import ledger as run_ledger

    # temporaries a killed run left behind (atomic writes, the .rrd's partial save): never
    # artefacts; a run folder has one run at a time, so they are stale
    for stale in run_ledger.temporaries(out):
        stale.unlink(missing_ok=True)
    P = run_paths(out)
    ctx = Context(
        out,
        configs={INGEST: ingest_configs(cfg)},
        recording=recording,
        recording_hash=str(fp["recording"]),
        tolerance_mm=cfg.tolerance_mm,
        force=force,
        ledger=True,
        progress=progress,
    )
    if REPORT in names and TOUCHUPS in names:
        from pipeline.report.warm import WarmReport

        # loads the Rerun SDK on the core ingest leaves idle (pipeline.report.warm), and
        # computes the report's code digest there, where its modules are loaded anyway
        ctx.warm_report = WarmReport.start(partial(stage_code_digest, REPORT))
        if ctx.warm_report is not None:  # the frames it will show, once they are known
            ctx.after_stage.setdefault(TOUCHUPS, []).append(ctx.warm_report.prefetch)
    try:
        key = _run_plan(ctx, cfg, names, recording, fp)
    except VtcalError as exc:  # a refusal: nothing partial stays (pipeline.run.withdraw)
        warned = _ingest_warnings(out)
        withdraw(out, before)
        if warned:  # still one line: a truncated recording is often why a later stage failed
            raise type(exc)(f"{exc} (ingest warned: {'; '.join(warned)})") from exc
        raise
    finally:
        if ctx.warm_report is not None:
            ctx.warm_report.close()
    # run.json's tolerance is the one the report judged with: none without a report
    tolerance = cfg.tolerance_mm if REPORT in names else None
    return _finish(out, P, ctx.records, key, fingerprint=fp, tolerance_mm=tolerance)


def _ingest_warnings(out: Path) -> list[str]:
    """The warnings in ``out/recording.json`` (none when absent or unreadable)."""
    try:
        data = json.loads((out / RUN_FILES["recording"]).read_text())
    except (OSError, ValueError):
        return []
    warned = data.get("warnings") if isinstance(data, dict) else None
    return [str(w) for w in warned] if isinstance(warned, list) else []


def _run_plan(
    ctx: Context, cfg: RunConfig, names: list[str], recording: Path, fp: dict[str, Any]
) -> dict[str, str] | None:
    """Ingest, then (steps 3-4 of :func:`run_pipeline`) the rest of the plan; the report's key."""
    P = run_paths(ctx.out)
    run_stages([INGEST], ctx, names)
    rest = names[1:]
    if rest:
        from pipeline.stages.ingest.stage import RecordingInfo

        info = RecordingInfo(**json.loads(P["recording"].read_text()))
        metadata_distances(info.metadata)  # bad values fail now
        if info.implausible and not cfg.stage_options.get(IDENTIFY, {}).get(
            "accept_implausible", False
        ):
            raise CalibrationFailed(
                f"{recording}: implausible input: "
                + "; ".join(info.implausible)
                + " (rerun with --accept-implausible if it is right)"
            )
        ctx.configs.update(stage_configs(cfg, info))
        ctx.robot = (info.urdf, info.base_link, info.flange_link)
        if CHOOSE in rest:
            ctx.source = _recording_source(recording, P["frames"], fp)
    return run_stages(rest, ctx, names)


def ingest_configs(cfg: RunConfig) -> dict[str, Any]:
    """The ingest stage's options: ``{"ingest": IngestConfig, "detect": DetectConfig}``
    (:func:`pipeline.run.runner.build_configs`, with the topics and metadata overrides)."""
    topics = {
        "image_topic": cfg.image_topic,
        "joint_topic": cfg.joint_topic,
        "description_topic": cfg.description_topic,
        "overrides": dict(cfg.overrides),
    }
    ingest = [s.name for s in catalog.STAGES if s.source]
    return dict(build_configs(ingest, cfg.stage_options, {n: topics for n in ingest})[ingest[0]])


def stage_configs(cfg: RunConfig, info: Any) -> dict[str, Any]:
    """The options of the stages after ingest, from ``cfg`` and the recording's metadata.

    Identify fits every model (cross-validation picks the one the run ships),
    with the recording's known distances (not strict: a truncated recording may
    not reach every target; strict when given on the command line) and its printed
    target size (the image-implied one identify reads from the touch-ups it declares,
    :func:`pipeline.stages.identify.node.identify`).
    """
    fixed = {
        IDENTIFY: {
            "model": "all",
            "distances": metadata_distances(info.metadata),
            # the recording's own distances may name a target a truncated run never
            # reached (dropped, noted); one typed on the command line must name a target
            "strict_distances": "known_distances" in cfg.overrides,
            "target_diameter_m": _diameter(info.metadata.get("target_diameter_m")),
        }
    }
    later = [s.name for s in catalog.STAGES if not s.source]
    return build_configs(later, cfg.stage_options, fixed)


def _recording_source(recording: Path, frames: Path, fp: Mapping[str, Any]) -> Any:
    """Provenance source of a run: the recording's name, hash, time and the run id."""
    import pyarrow.parquet as pq

    from pipeline.export.provenance import Source, recorded_utc

    stamps = pq.read_table(frames, columns=["stamp_ns"]).column("stamp_ns").to_pylist()
    return Source(
        kind="recording",
        name=recording.name,
        sha256=str(fp["recording"]),
        run_id=config_hash(dict(fp)),
        recorded_utc=recorded_utc(stamps),
    )


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
    from pipeline.run import ledger as run_ledger

    summary: dict[str, Any] = {}
    if P["identify"].exists():
        summary = json.loads(P["identify"].read_text())
    ledger: dict[str, Any] = {}
    if fingerprint is not None:
        ledger[run_ledger.KEY] = run_ledger.entry(
            out, fingerprint, [name for r in records for name in r.outputs]
        )
    write_run(out, records, report_inputs=report_inputs, tolerance_mm=tolerance_mm, **ledger)
    return RunResult(out, records, summary)


def _from_ledger(out: Path, fp: dict[str, Any]) -> RunResult | None:
    """The run as it stands in ``out`` when the run ledger vouches for ``fp``, else None.

    On a hit ``run.json`` is brought to what a run with every stage cached writes
    (statuses ``cached``; rewritten only when that changes its bytes).
    """
    from pipeline.run import ledger as run_ledger

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
        write_run(
            out,
            records,
            changed_only=True,
            report_inputs=run.get("report_inputs"),
            tolerance_mm=run.get("tolerance_mm"),
            **{run_ledger.KEY: run[run_ledger.KEY]},
        )
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
    from pipeline.run import ledger as run_ledger

    try:
        recording, out = Path(recording), Path(out)
        if (until is not None and until not in STAGES) or not recording.exists():
            return None
        fp = run_ledger.fingerprint(recording, config or RunConfig(), until)
        return _from_ledger(out, fp)
    except (OSError, ValueError, BadInput):
        return None
