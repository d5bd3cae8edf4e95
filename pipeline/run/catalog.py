"""The declared pipeline: every stage, declared once.

:data:`STAGES` is the pipeline as a table of :class:`Stage`: the function
that computes it, the artefacts it reads and those it writes, and the config
dataclass of its options. The files of a run folder (their names, schemas and
writers) are declared below it, in :mod:`pipeline.io.run_folder`
(:data:`~pipeline.io.run_folder.ARTEFACTS`), which the readers of a run folder
import without the stage table. The runner (:mod:`pipeline.run.runner`) walks this
table; stage functions take data and return data, and only the runner writes.
``tests/test_catalog.py`` checks that every file has exactly one writer and
that each stage reads only what an earlier stage wrote.

Cheap to import: ``vtcal run``'s options and the run ledger read the catalogue
without importing the runner or a stage's computation. Each stage's function is
held itself (``Stage.fn``: its node, ``node.py`` in the stage's package, which
imports only the standard library and :mod:`pipeline.io.run_folder` at module level
and the stage's computation inside the function); configs and code entry points
are :class:`~pipeline.run.lazy.Ref` (their modules are the heavy ones: the runner
loads a config class when it builds the options, :mod:`pipeline.run.code_key` the
entry functions when it keys a stage, and reads their modules' import closure).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pipeline.io.run_folder import ARTEFACTS, BY_KEY, RUN_FILES, Artefact
from pipeline.report import node as report_node
from pipeline.run.lazy import Ref
from pipeline.stages.choose import node as choose_node
from pipeline.stages.crossval import node as crossval_node
from pipeline.stages.identify import node as identify_node
from pipeline.stages.ingest import node as ingest_node
from pipeline.stages.outliers import node as outliers_node
from pipeline.stages.touchups import node as touchups_node

#: the stage names, each written once, here: code that names a stage uses these
#: (``tests/test_stage_literals.py`` fails on a stage name typed as a string elsewhere)
INGEST = "ingest"
TOUCHUPS = "touchups"
OUTLIERS = "outliers"
IDENTIFY = "identify"
CROSSVAL = "crossval"
CHOOSE = "choose"
REPORT = "report"

#: a stage's function: ``fn(data, config, context, **other_configs) -> {artefact key: value}``
#: (``other_configs``: those of :attr:`Stage.uses_configs`)
Node = Callable[..., dict[str, Any]]


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline.

    Attributes
    ----------
    name : the stage's name (``--until`` takes it)
    fn : the function computing it, its node (``node.py`` in the stage's package):
        ``fn(data, config, context) -> {key: value}`` with ``data`` the artefacts of
        ``inputs`` (tables and dicts) and the result holding one value per key of
        ``outputs``
    inputs : artefact keys it reads (each written by an earlier stage)
    outputs : artefact keys it writes (it is their only writer), in the order they are
        written after its Parquet ones: the last present means the stage finished
    config : its options dataclass (a :class:`~pipeline.run.lazy.Ref` to it), or None
    code : further entry functions whose code decides its result (the stage code key,
        :mod:`pipeline.run.code_key`): each the function, or a
        :class:`~pipeline.run.lazy.Ref` to it (loaded when the key is computed)
    optional : inputs it reads only when their stage is part of the run
    cache : how the runner keys it. ``"outputs"``: fresh when its Parquet outputs record
        the same input hashes and config (:func:`pipeline.run.runner.is_fresh`);
        ``"always"``: cheap, computed every run, a file rewritten only when its bytes
        change; ``"ledger"``: keyed in ``run.json`` (its files are written by their own
        writers, and it shows the stage table, so it runs last)
    source : it reads the recording itself (not an artefact): its cache key is the
        recording's content hash
    follows : a stage after which this one always runs when that one is planned
        (``--until`` stopping between them still ships its result)
    uses_configs : earlier stages whose options this stage's function takes too, handed
        over by the runner as keyword arguments named as those stages (crossval refits
        with identify's options: ``fn(data, config, context, identify=...)``); they are
        not part of this stage's cache key (the outputs of those stages it reads are)
    sub_configs : further option groups ``(name, Ref(module, Class))`` of a stage whose
        options are several dataclasses (ingest: ``detect``); its config is then
        ``{name: options, group: options, ...}``
    """

    name: str
    fn: Node
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    config: Ref | None
    code: tuple[Ref | Callable[..., Any], ...] = ()
    optional: tuple[str, ...] = ()
    cache: str = "outputs"
    source: bool = False
    follows: str | None = None
    sub_configs: tuple[tuple[str, Ref], ...] = ()
    uses_configs: tuple[str, ...] = ()

    @property
    def fn_name(self) -> str:
        """``module:function`` of :attr:`fn` (what the stage code key names it by)."""
        return f"{self.fn.__module__}:{self.fn.__qualname__}"

    @property
    def option_groups(self) -> tuple[str, ...]:
        """The names ``--set GROUP.OPTION=VALUE`` reaches this stage's options by."""
        own = (self.name,) if self.config else ()
        return own + tuple(g for g, _ in self.sub_configs)


#: the pipeline, in run order
STAGES: list[Stage] = [
    Stage(
        INGEST,
        ingest_node.ingest,
        (),
        ("frames", "detections", "recording"),
        Ref("pipeline.stages.ingest.stage", "IngestConfig"),
        (Ref("pipeline.stages.ingest.stage", "ingest_recording"),),
        source=True,
        sub_configs=(("detect", Ref("pipeline.stages.detect.detector", "DetectConfig")),),
    ),
    Stage(
        TOUCHUPS,
        touchups_node.touchups,
        ("frames", "detections", "recording"),
        ("touchups",),
        Ref("pipeline.stages.touchups.stage", "TouchupConfig"),
        (Ref("pipeline.stages.touchups.stage", "extract_touchups"),),
    ),
    Stage(
        OUTLIERS,
        outliers_node.outliers,
        ("touchups", "recording"),
        ("inliers",),
        Ref("pipeline.stages.outliers.stage", "OutlierConfig"),
        (Ref("pipeline.stages.outliers.stage", "flag_outliers"),),
    ),
    Stage(
        IDENTIFY,
        identify_node.identify,
        ("inliers",),
        ("parameters", "residuals", "targets", "model_urdfs", "models"),
        Ref("pipeline.stages.identify.stage", "IdentifyConfig"),
        (Ref("pipeline.stages.identify.stage", "identify"),),
        # touchups: the target diameter its image Jacobian implies (the guardrails check it)
        optional=("touchups",),
    ),
    Stage(
        CROSSVAL,
        crossval_node.crossval,
        ("inliers", "parameters", "models"),
        ("crossval",),
        Ref("pipeline.stages.crossval.stage", "CrossvalConfig"),
        (Ref("pipeline.stages.crossval.stage", "cross_validate"),),
        uses_configs=(IDENTIFY,),  # its refits fit as identify did
    ),
    Stage(
        CHOOSE,
        choose_node.choose,
        ("models", "model_urdfs", "parameters"),
        ("calibrated_urdf", "calibration", "identify"),
        None,
        (
            Ref("pipeline.stages.choose.stage", "choose_model"),
            Ref("pipeline.use.record", "calibration_record"),
        ),
        # touchups: the repeated captures' noise; recording: the assumptions (adequacy)
        optional=("crossval", "touchups", "recording"),
        cache="always",
        follows=IDENTIFY,
    ),
    Stage(
        REPORT,
        report_node.report,
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
            Ref("pipeline.report.html", "build_report"),
            Ref("pipeline.report.rrd", "build_rrd"),
            Ref("pipeline.report.outputs", "build_outputs"),
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
