"""The files of a run folder: each declared once, with its schema and its one writer.

:data:`ARTEFACTS` names each file of a run folder (``spec/outputs.md``), its
schema (``schemas/NAME.json`` for Parquet) and the stage that writes it;
:data:`RUN_FILES` maps an artefact key to its file name. Every module that
opens a run-folder file names it through :data:`RUN_FILES`
(``tests/test_catalog.py`` fails on a name typed by hand elsewhere), and
:class:`Parquet` is a stage's Parquet output before the runner writes it.

Pure facts about file names, standard library only, at the bottom of the
package: the report, the exports, ``vtcal validate``, the simulator and the
batch read it without importing the run's machinery. The stage table
(:data:`pipeline.run.catalog.STAGES`) sits above, in the run's machinery; a stage it
registers adds its files here (:func:`pipeline.run.catalog.register`), in place.
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


def parquet_meta(data: Any, key: str) -> dict[str, str]:
    """The ``vtcal.*`` metadata of Parquet input ``key`` of a stage's node; from the runner's
    inputs without reading the table's rows (:meth:`pipeline.run.runner.Inputs.meta`), else
    from the table's ``attrs``."""
    meta = getattr(data, "meta", None)
    return dict(meta(key)) if meta is not None else dict(data[key].attrs["vtcal"])


def writer(key: str) -> str:
    """The stage that writes artefact ``key`` (a KeyError names an undeclared file)."""
    return BY_KEY[key].writer


def run_paths(out: Path) -> dict[str, Path]:
    """The files a run folder holds, as paths under ``out``."""
    return {k: out / v for k, v in RUN_FILES.items()}
