"""What every export format starts from: a run folder's shipped calibration, read once.

This module is the disk edge of :mod:`pipeline.export`; the format modules are
pure functions of a :class:`RunCalibration`. Everything comes from four files
of the run folder (``spec/outputs.md``):

* ``calibrated.urdf``: the shipped model's chain (base link to flange link), the
  virtual pin (the ``virtual_pin_joint`` origin) and the provenance block;
* ``identify.json``: the shipped model, its figures and every model's summary;
* ``calibration.json``: the model predictions use (``elastic``'s compliance where
  the run chose it; the ``json`` format carries it whole);
* ``parameters.parquet``: the ``offsets`` model's joint zero offsets and pin
  (identified with the nominal link geometry, so they are what a controller
  that keeps its own kinematics can use).

The base link is ``recording.json``'s (``vtcal run``) or else the URDF's root
link (``vtcal identify``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BadInput
from pipeline.export.provenance import read_provenance
from pipeline.io.run_folder import RUN_FILES
from pipeline.kinematics.chain import Chain, load_chain
from pipeline.kinematics.se3 import F64
from pipeline.kinematics.urdf import parse_urdf
from pipeline.kinematics.urdf_write import PIN_JOINT


@dataclass(frozen=True)
class OffsetsFit:
    """The ``offsets`` model of a run: zero offsets with the nominal link geometry.

    Attributes
    ----------
    joints : actuated joint names, chain order
    dq0 : (n,) zero offsets (rad; m for a prismatic joint), 0 where not identifiable
    units : (n,) ``"rad"`` or ``"m"``
    identifiable : (n,) bool; False: held at 0 (absorbed by the base frame or the pin)
    std : (n,) standard deviations (NaN where held)
    p_flange_pin : (3,) virtual pin in the NOMINAL flange frame, m
    """

    joints: tuple[str, ...]
    dq0: F64
    units: tuple[str, ...]
    identifiable: np.ndarray
    std: F64
    p_flange_pin: F64


@dataclass(frozen=True)
class RunCalibration:
    """A run folder's shipped calibration (see module docstring)."""

    run_dir: Path
    calibrated_urdf: str
    base_link: str
    flange_link: str
    chain: Chain = field(repr=False)
    p_flange_pin: F64
    summary: dict[str, Any] = field(repr=False)
    provenance: dict[str, str]
    offsets: OffsetsFit | None = None
    #: ``calibration.json`` (the model predictions use, :mod:`pipeline.use.record`), if present
    record: dict[str, Any] | None = field(default=None, repr=False)

    @property
    def model(self) -> str:
        return str(self.summary.get("best_model") or self.summary.get("model") or "")


def _root_link(xml: str) -> str:
    robot = parse_urdf(xml)
    children = {j.child for j in robot.joints.values()}
    roots = sorted({j.parent for j in robot.joints.values() if j.parent not in children})
    if len(roots) != 1:
        raise BadInput(f"calibrated.urdf has {len(roots)} root links {roots}")
    return roots[0]


def _pin(xml: str) -> tuple[str, F64]:
    robot = parse_urdf(xml)
    joint = robot.joints.get(PIN_JOINT)
    if joint is None:
        raise BadInput(f"calibrated.urdf has no {PIN_JOINT!r} (not written by vtcal?)")
    return joint.parent, np.asarray(joint.T_parent_joint[:3, 3], dtype=float)


def _offsets(run_dir: Path, joints: list[str]) -> OffsetsFit | None:
    path = run_dir / RUN_FILES["parameters"]
    if not path.is_file():
        return None
    import pandas as pd

    try:
        df = pd.read_parquet(path)
    except Exception as exc:  # pyarrow raises many types for a damaged file
        raise BadInput(f"{path}: not a readable parameters artefact: {exc}") from exc
    rows = df[df["model"] == "offsets"]
    if rows.empty:
        return None
    by_name = {str(r["name"]): r for _, r in rows.iterrows()}
    dq0, units, ident, std = [], [], [], []
    for jn in joints:
        r = by_name.get(f"{jn}.dq0")
        if r is None:
            raise BadInput(f"{path}: the offsets model has no row {jn}.dq0")
        ok = bool(r["identifiable"])
        dq0.append(float(r["value"]) if ok else 0.0)
        units.append(str(r["unit"]))
        ident.append(ok)
        std.append(float(r["std"]) if ok else float("nan"))
    try:
        pin = np.array([float(by_name[f"pin.{c}"]["value"]) for c in "xyz"])
    except KeyError as exc:
        raise BadInput(f"{path}: the offsets model has no pin row {exc}") from exc
    return OffsetsFit(
        joints=tuple(joints),
        dq0=np.array(dq0),
        units=tuple(units),
        identifiable=np.array(ident, dtype=bool),
        std=np.array(std),
        p_flange_pin=pin,
    )


def load_run(run_dir: str | Path) -> RunCalibration:
    """Read a run folder's shipped calibration.

    Raises
    ------
    BadInput
        Naming the file: no such folder, no ``calibrated.urdf`` or ``identify.json``,
        or one that does not parse.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise BadInput(f"{run_dir}: no such run folder")
    urdf_path, id_path = run_dir / RUN_FILES["calibrated_urdf"], run_dir / RUN_FILES["identify"]
    for p in (urdf_path, id_path):
        if not p.is_file():
            raise BadInput(f"{p}: missing (run 'vtcal run' or 'vtcal identify' first)")
    try:
        xml = urdf_path.read_text()
        flange, pin = _pin(xml)
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{urdf_path}: cannot read: {exc}") from exc
    except BadInput as exc:
        raise BadInput(f"{urdf_path}: {exc}") from exc
    try:
        summary = json.loads(id_path.read_text())
    except (OSError, ValueError) as exc:
        raise BadInput(f"{id_path}: not readable JSON: {exc}") from exc
    base = None
    rec = run_dir / RUN_FILES["recording"]
    if rec.is_file():
        try:
            base = json.loads(rec.read_text()).get("base_link")
        except (OSError, ValueError) as exc:
            raise BadInput(f"{rec}: not readable JSON: {exc}") from exc
    try:
        base = str(base) if base else _root_link(xml)
        chain = load_chain(xml, base, flange)
    except BadInput as exc:
        raise BadInput(f"{urdf_path}: {exc}") from exc
    return RunCalibration(
        run_dir=run_dir,
        calibrated_urdf=xml,
        base_link=base,
        flange_link=flange,
        chain=chain,
        p_flange_pin=pin,
        summary=summary,
        provenance=read_provenance(xml),
        offsets=_offsets(run_dir, chain.joint_names),
        record=_record(run_dir),
    )


def _record(run_dir: Path) -> dict[str, Any] | None:
    """The run's ``calibration.json``, None in a run folder from before it existed."""
    path = run_dir / RUN_FILES["calibration"]
    if not path.is_file():
        return None
    try:
        record: dict[str, Any] = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BadInput(f"{path}: not readable JSON: {exc}") from exc
    return record


def header_lines(cal: RunCalibration) -> list[str]:
    """Provenance of ``cal`` as plain lines (for a format's comment header)."""
    lines = [f"{k}: {v}" for k, v in cal.provenance.items()]
    return lines or [f"shipped model: {cal.model} (calibrated.urdf has no provenance block)"]
