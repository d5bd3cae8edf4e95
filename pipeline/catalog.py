"""The declared pipeline: every run-folder file and every stage, each declared once.

:data:`ARTEFACTS` names each file of a run folder (``spec/outputs.md``),
its schema (``schemas/NAME.json`` for Parquet) and the one stage that writes
it. :data:`STAGES` is the pipeline as a table of :class:`Stage`: the function
that computes it, the artefacts it reads and those it writes, and the config
dataclass of its options. The runner (:mod:`pipeline.runner`) walks this
table; stage functions take data and return data, and only the runner writes.
``tests/test_catalog.py`` checks that every file has exactly one writer and
that each stage reads only what an earlier stage wrote.

Standard library only: the report, ``vtcal validate``, ``vtcal compare``, the
batch and the run ledger read the catalogue without importing the runner or
a stage (functions and configs are named ``module:attribute``, resolved by
the runner).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Artefact:
    """One file of a run folder.

    Attributes
    ----------
    key : the name stages and readers use (``"parameters"``)
    file : file name inside the run folder (``"parameters.parquet"``)
    writer : the stage that writes it (``"runner"``: the runner's own ledger)
    schema : declared Parquet schema (``schemas/SCHEMA.json``), None for other files
    keyed : its hash is part of the cache key of the stages that read it. False
        for a side file whose results its writer's Parquet outputs (read too)
        already key, and which holds wall-clock timings: keying on it would
        make a reader's Parquet bytes differ from run to run
    index : for a file per fitted model (``file`` holds ``{model}``): the JSON
        artefact whose ``"models"`` list names the models, so the files
    """

    key: str
    file: str
    writer: str
    schema: str | None = None
    keyed: bool = True
    index: str | None = None

    @property
    def per_model(self) -> bool:
        """One file per fitted model (``file`` is a pattern, :attr:`index` names them)."""
        return "{model}" in self.file


#: every file of a run folder, in the order the stages write them
ARTEFACTS: list[Artefact] = [
    Artefact("frames", "frames.parquet", "ingest", "frames"),
    Artefact("detections", "detections.parquet", "ingest", "detections"),
    Artefact("recording", "recording.json", "ingest"),
    Artefact("touchups", "touchups.parquet", "touchups", "touchups"),
    Artefact("inliers", "inliers.parquet", "outliers", "inliers"),
    Artefact("parameters", "parameters.parquet", "identify", "parameters"),
    Artefact("residuals", "residuals.parquet", "identify", "residuals"),
    Artefact("targets", "targets.parquet", "identify", "targets"),
    Artefact("models", "models.json", "identify", keyed=False),
    Artefact("model_urdfs", "calibrated_{model}.urdf", "identify", index="models"),
    Artefact("crossval", "crossval.parquet", "crossval", "crossval"),
    Artefact("calibrated_urdf", "calibrated.urdf", "choose"),
    Artefact("calibration", "calibration.json", "choose"),
    Artefact("identify", "identify.json", "choose"),
    Artefact("report", "report.html", "report"),
    Artefact("rrd", "run.rrd", "report"),
    Artefact("run", "run.json", "runner"),
]

#: artefact key -> file name inside a run folder (``spec/outputs.md``);
#: the per-model URDFs (``Artefact.per_model``) are named by the models fitted
RUN_FILES = {a.key: a.file for a in ARTEFACTS if "{" not in a.file}

#: artefact key -> its declaration
BY_KEY = {a.key: a for a in ARTEFACTS}


@dataclass(frozen=True)
class Parquet:
    """A stage's Parquet output: the rows and further ``vtcal.*`` metadata strings."""

    data: Any
    meta: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline.

    Attributes
    ----------
    name : the stage's name (``--until`` takes it)
    fn : ``module:function`` computing it: ``fn(data, config, context) -> {key: value}``
        with ``data`` the artefacts of ``inputs`` (tables and dicts) and the
        result holding one value per key of ``outputs``
    inputs : artefact keys it reads (each written by an earlier stage)
    outputs : artefact keys it writes (it is their only writer), in the order they are
        written after its Parquet ones: the last present means the stage finished
    config : ``module:Class`` of its options dataclass, or None
    code : further ``module:function`` entry points whose code decides its result
        (the stage code key, :mod:`pipeline.code_key`)
    optional : inputs it reads only when their stage is part of the run
    cache : how the runner keys it. ``"outputs"``: fresh when its Parquet outputs record
        the same input hashes and config (:func:`pipeline.runner.is_fresh`);
        ``"always"``: cheap, computed every run, a file rewritten only when its bytes
        change; ``"ledger"``: keyed in ``run.json`` (its files are written by their own
        writers, and it shows the stage table, so it runs last)
    source : it reads the recording itself (not an artefact): its cache key is the
        recording's content hash
    follows : a stage after which this one always runs when that one is planned
        (``--until`` stopping between them still ships its result)
    sub_configs : further option groups ``(name, "module:Class")`` of a stage whose
        options are several dataclasses (ingest: ``detect``); its config is then
        ``{name: options, group: options, ...}``
    """

    name: str
    fn: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    config: str | None
    code: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()
    cache: str = "outputs"
    source: bool = False
    follows: str | None = None
    sub_configs: tuple[tuple[str, str], ...] = ()

    @property
    def option_groups(self) -> tuple[str, ...]:
        """The names ``--set GROUP.OPTION=VALUE`` reaches this stage's options by."""
        own = (self.name,) if self.config else ()
        return own + tuple(g for g, _ in self.sub_configs)


#: the pipeline, in run order
STAGES: list[Stage] = [
    Stage(
        "ingest",
        "pipeline.nodes:ingest",
        (),
        ("frames", "detections", "recording"),
        "pipeline.stages.ingest.stage:IngestConfig",
        ("pipeline.stages.ingest.stage:ingest_recording",),
        source=True,
        sub_configs=(("detect", "pipeline.stages.detect.detector:DetectConfig"),),
    ),
    Stage(
        "touchups",
        "pipeline.nodes:touchups",
        ("frames", "detections", "recording"),
        ("touchups",),
        "pipeline.stages.touchup.stage:TouchupConfig",
        ("pipeline.stages.touchup.stage:extract_touchups",),
    ),
    Stage(
        "outliers",
        "pipeline.nodes:outliers",
        ("touchups", "recording"),
        ("inliers",),
        "pipeline.stages.trust.outliers:OutlierConfig",
        ("pipeline.stages.trust.outliers:flag_outliers",),
    ),
    Stage(
        "identify",
        "pipeline.nodes:identify",
        ("inliers",),
        ("parameters", "residuals", "targets", "model_urdfs", "models"),
        "pipeline.stages.identify.stage:IdentifyConfig",
        ("pipeline.stages.identify.stage:identify",),
        # touchups: the target diameter its image Jacobian implies (the guardrails check it)
        optional=("touchups",),
    ),
    Stage(
        "crossval",
        "pipeline.nodes:crossval",
        ("inliers", "parameters", "models"),
        ("crossval",),
        "pipeline.stages.crossval.stage:CrossvalConfig",
        ("pipeline.stages.crossval.stage:cross_validate",),
    ),
    Stage(
        "choose",
        "pipeline.nodes:choose",
        ("models", "model_urdfs", "parameters"),
        ("calibrated_urdf", "calibration", "identify"),
        None,
        ("pipeline.stages.crossval.choose:choose_model", "pipeline.use.record:calibration_record"),
        # touchups: the repeated captures' noise; recording: the assumptions (adequacy)
        optional=("crossval", "touchups", "recording"),
        cache="always",
        follows="identify",
    ),
    Stage(
        "report",
        "pipeline.nodes:report",
        (
            "recording",
            "touchups",
            "inliers",
            "parameters",
            "residuals",
            "targets",
            "crossval",
            "identify",
            "calibrated_urdf",
        ),
        ("report", "rrd"),
        None,
        (
            "pipeline.report.html:build_report",
            "pipeline.report.rrd:build_rrd",
            "pipeline.report.outputs:build_outputs",
        ),
        cache="ledger",
    ),
]

#: stage name -> its declaration
STAGE = {s.name: s for s in STAGES}

#: the stage names, in run order
STAGE_NAMES = [s.name for s in STAGES]


def register(stage: Stage, *artefacts: Artefact) -> None:
    """Add a stage at the end of the pipeline, with the files it writes (in place: every
    reader of the tables above sees it). What a new stage needs besides is its function
    (``Stage.fn``) and, for a Parquet file, its schema (``schemas/NAME.json``):
    ``tests/test_catalog.py`` registers a throw-away one."""
    if stage.name in STAGE or any(
        a.key in BY_KEY or a.file in RUN_FILES.values() for a in artefacts
    ):
        raise ValueError(f"stage {stage.name!r} or one of its files is declared already")
    ARTEFACTS.extend(artefacts)
    BY_KEY.update({a.key: a for a in artefacts})
    RUN_FILES.update({a.key: a.file for a in artefacts if "{" not in a.file})
    STAGES.append(stage)
    STAGE[stage.name] = stage
    STAGE_NAMES.append(stage.name)


def unregister(name: str) -> None:
    """Remove a stage :func:`register` added, and the files it writes."""
    stage = STAGE.pop(name)
    STAGES.remove(stage)
    STAGE_NAMES.remove(name)
    for key in stage.outputs:
        ARTEFACTS.remove(BY_KEY.pop(key))
        RUN_FILES.pop(key, None)


def option_groups() -> list[str]:
    """Every name ``--set GROUP.OPTION=VALUE`` takes (:attr:`Stage.option_groups`)."""
    return [g for s in STAGES for g in s.option_groups]


def writer(key: str) -> str:
    """The stage that writes artefact ``key`` (a KeyError names an undeclared file)."""
    return BY_KEY[key].writer


def run_paths(out: Path) -> dict[str, Path]:
    """The files a run folder holds, as paths under ``out``."""
    return {k: out / v for k, v in RUN_FILES.items()}
