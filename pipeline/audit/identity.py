"""Which runs are one robot's history: robot identity, robot model and date.

A run folder (``vtcal run``, ``vtcal batch``, or :func:`pipeline.sim.history.write_history`)
holds ``recording.json`` and ``inliers.parquet``. Its robot is

* **identity**: the recording's ``robot_id`` metadata key
  (``spec/recording.md``), else the ``robot_id`` of its entry in the batch
  manifest (the entry whose run folder name it has), else the ``--robot-id``
  given for all inputs;
* **model**: the nominal URDF's ``<robot name>``, its chain ends and joint names
  (two robots of one model share it; a history must not mix models);
* **date**: the first stamp (``recording.json``'s ``first_stamp_ns`` when
  written, else the first frame's ``stamp_ns`` in ``frames.parquet``, else the
  earliest touch-up's).

Runs of one identity, sorted by date, are its history.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.errors import BadInput
from pipeline.io.run_folder import RUN_FILES

RECORDING = RUN_FILES["recording"]
INLIERS = RUN_FILES["inliers"]
TOUCHUPS = RUN_FILES["touchups"]


@dataclass
class AuditItem:
    """One recording as the audit reads it.

    Attributes
    ----------
    name : the run folder's name ; path : the folder
    robot_id : the physical robot ; model : ``ROBOT_NAME(joint, ...)`` of the nominal URDF
    urdf, base_link, flange_link : the nominal chain
    stamp_ns : the recording's first stamp
    table : its touch-ups (``inliers.parquet``)
    distances : known distances ``(a, b, metres)`` from its metadata
    truth : ``truth.json`` beside it when simulated (None otherwise; the benchmark reads it)
    noise : the touch-up stage's measured noise (``capture_noise`` of ``touchups.parquet``,
        :mod:`pipeline.stages.touchups.noise`), None where the folder lacks it
    table_read : False when :func:`load_item` left ``table`` unread (empty) for a
        worker to read (:func:`with_table`)
    """

    name: str
    path: Path
    robot_id: str
    model: str
    urdf: str
    base_link: str
    flange_link: str
    stamp_ns: int
    table: pd.DataFrame
    distances: list[tuple[Any, Any, float]] = field(default_factory=list)
    truth: dict[str, Any] | None = None
    noise: dict[str, Any] | None = None
    table_read: bool = True


def robot_name(urdf: str) -> str:
    """The ``<robot name=...>`` of a URDF ('' when absent)."""
    m = re.search(r"<robot[^>]*\bname\s*=\s*[\"']([^\"']*)[\"']", urdf)
    return m.group(1) if m else ""


def run_folders(paths: list[Path]) -> list[Path]:
    """The run folders named: a folder with ``recording.json``, or each such sub-folder of
    a folder (a ``vtcal batch`` output), sorted by name.

    Raises
    ------
    BadInput
        A path that is neither.
    """
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if (p / RECORDING).is_file():
            out.append(p)
            continue
        subs = sorted(d for d in p.iterdir() if (d / RECORDING).is_file()) if p.is_dir() else []
        if not subs:
            raise BadInput(f"{p}: not a run folder (no {RECORDING}) nor a folder of run folders")
        out.extend(subs)
    return out


def _first_stamp(folder: Path, rec: dict[str, Any], table: pd.DataFrame) -> int:
    if "first_stamp_ns" in rec:
        return int(rec["first_stamp_ns"])
    frames = folder / RUN_FILES["frames"]
    if frames.is_file():
        import pyarrow.parquet as pq

        col = pq.read_table(frames, columns=["stamp_ns"]).column(0)
        if len(col):
            return int(min(col.to_pylist()))
    if "stamp_ns" in table.columns and len(table):
        return int(table["stamp_ns"].min())
    raise BadInput(f"{folder}: no stamp to date the recording by (frames.parquet, stamp_ns)")


def manifest_ids(path: Path) -> dict[str, str]:
    """``{run folder name: robot_id}`` of a batch manifest's entries that give one."""
    from pipeline.batch.manifest import load_manifest

    return {it.name: it.robot_id for it in load_manifest(path).items if it.robot_id}


def load_item(
    folder: Path,
    robot_id: str | None = None,
    ids: dict[str, str] | None = None,
    *,
    table: bool = True,
) -> AuditItem:
    """Read one run folder (``ids``: :func:`manifest_ids`; ``robot_id``: for all).

    ``table=False`` leaves the touch-ups unread where the recording is dated without
    them (the audit reads them where a fit runs, :func:`with_table`; a cached one
    needs none).

    Raises
    ------
    BadInput
        No ``inliers.parquet``, unreadable ``recording.json``, or no robot identity
        (neither the ``robot_id`` metadata key nor ``robot_id`` given).
    """
    from pipeline.io.artefacts import read_artefact
    from pipeline.io.known_distances import metadata_distances

    folder = Path(folder)
    try:
        rec = json.loads((folder / RECORDING).read_text())
    except (OSError, ValueError) as exc:
        raise BadInput(f"{folder / RECORDING}: not readable JSON: {exc}") from exc
    if not (folder / INLIERS).is_file():
        raise BadInput(f"{folder}: no {INLIERS} (run the recording up to the outliers stage)")
    meta = dict(rec.get("metadata") or {})
    rid = str(meta.get("robot_id") or (ids or {}).get(folder.name) or robot_id or "")
    if not rid:
        raise BadInput(
            f"{folder / RECORDING}: no robot_id (the recording's metadata key robot_id, "
            "spec/recording.md, or its batch manifest entry's); give --manifest "
            "FILE.toml or --robot-id NAME"
        )
    lazy = not table and ("first_stamp_ns" in rec or (folder / RUN_FILES["frames"]).is_file())
    touchups = pd.DataFrame() if lazy else read_artefact(folder / INLIERS, "inliers")
    urdf = str(rec.get("urdf", ""))
    joints = list(rec.get("joint_names") or [])
    base, flange = str(rec.get("base_link", "")), str(rec.get("flange_link", ""))
    truth_path = folder / "truth.json"
    return AuditItem(
        name=folder.name,
        path=folder,
        robot_id=rid,
        model=f"{robot_name(urdf) or '?'}({base}->{flange}: {','.join(joints)})",
        urdf=urdf,
        base_link=base,
        flange_link=flange,
        stamp_ns=_first_stamp(folder, rec, touchups),
        table=touchups,
        distances=metadata_distances(meta),
        truth=json.loads(truth_path.read_text()) if truth_path.is_file() else None,
        noise=measured_noise(folder / TOUCHUPS),
        table_read=not lazy,
    )


def with_table(item: AuditItem) -> AuditItem:
    """``item`` with its touch-ups read (:func:`load_item` with ``table=False`` leaves them)."""
    if item.table_read:
        return item
    from dataclasses import replace

    from pipeline.io.artefacts import read_artefact

    return replace(item, table=read_artefact(item.path / INLIERS, "inliers"), table_read=True)


def measured_noise(path: Path) -> dict[str, Any] | None:
    """The ``capture_noise`` metadata of a run folder's ``touchups.parquet`` (the touch-up
    stage's measured noise, :mod:`pipeline.stages.touchups.noise`), None where the file or
    the key is missing or unreadable."""
    if not path.is_file():
        return None
    import pyarrow as pa

    from pipeline.io.artefacts import read_meta

    try:
        raw = read_meta(path).get("capture_noise")
        out = json.loads(raw) if raw else None
    except (OSError, ValueError, pa.ArrowInvalid):
        return None
    return out if isinstance(out, dict) else None


def histories(items: list[AuditItem]) -> dict[str, list[AuditItem]]:
    """``{robot_id: its recordings, oldest first}`` (robot ids sorted).

    Raises
    ------
    BadInput
        Recordings of one robot_id whose robot models differ (names both).
    """
    out: dict[str, list[AuditItem]] = {}
    for it in items:
        out.setdefault(it.robot_id, []).append(it)
    for rid, runs in out.items():
        models = {r.model for r in runs}
        if len(models) > 1:
            a = runs[0]
            b = next(r for r in runs if r.model != a.model)
            raise BadInput(
                f"{b.path}: robot_id {rid!r} is model {b.model} but {a.path} of the same "
                f"robot_id is model {a.model}: one robot cannot change model"
            )
        runs.sort(key=lambda r: (r.stamp_ns, r.name))
    return dict(sorted(out.items()))
