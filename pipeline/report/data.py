"""Everything the report and the Rerun recording show, read from a run folder only.

A run folder (``spec/outputs.md``) holds one artefact per stage. The
report never re-solves anything: it reads what is there, and a section whose
artefact is missing (an interrupted run, ``--until``, a stage not built yet)
says "not available" instead of failing. :func:`load_run` gathers every
artefact into a :class:`RunData`; the helpers below turn it into the few
derived figures both outputs need (accuracy summary, per-pose pin positions,
a deterministic run id).
"""

from __future__ import annotations

import hashlib
import json
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from pipeline.io.artefacts import SCHEMA_DIR, file_hash, read_artefact
from pipeline.io.run_folder import RUN_FILES
from pipeline.kinematics.chain import Chain, load_chain
from pipeline.kinematics.urdf import RobotDescription, parse_urdf

#: artefact name -> file name inside a run folder, by kind (names from the catalogue);
#: models.json is identify's input to the choice: identify.json holds all it says
PARQUET = {k: v for k, v in RUN_FILES.items() if v.endswith(".parquet")}
JSONS = {k: RUN_FILES[k] for k in ("recording", "identify", "run")}
TEXTS = {"calibrated_urdf": RUN_FILES["calibrated_urdf"]}
#: files whose content the outputs show: their hashes make the deterministic recording id
#: (run.json is left out: it holds wall-clock timings, not results)
INPUT_FILES = tuple(
    sorted([*PARQUET.values(), *TEXTS.values(), JSONS["recording"], JSONS["identify"]])
)

PIN_LINK = "virtual_pin"


@dataclass
class RunData:
    """The artefacts of one run folder (``None`` where a file is missing or unreadable).

    Attributes
    ----------
    run_dir : Path
    recording, identify, run : dict or None
        ``recording.json``, ``identify.json``, ``run.json``.
    frames, detections, touchups, inliers, parameters, residuals, targets, crossval
        : DataFrame or None
    calibrated_urdf : str or None
        XML of ``calibrated.urdf``.
    problems : list of str
        One line per artefact that exists but could not be read.
    derived : dict
        Figures derived from the artefacts, computed once per load and shared by the
        sections that show them (e.g. ``nominal_fit``: the report's "before").
    """

    run_dir: Path
    recording: dict[str, Any] | None = None
    identify: dict[str, Any] | None = None
    run: dict[str, Any] | None = None
    frames: pd.DataFrame | None = None
    detections: pd.DataFrame | None = None
    touchups: pd.DataFrame | None = None
    inliers: pd.DataFrame | None = None
    parameters: pd.DataFrame | None = None
    residuals: pd.DataFrame | None = None
    targets: pd.DataFrame | None = None
    crossval: pd.DataFrame | None = None
    calibrated_urdf: str | None = None
    problems: list[str] = field(default_factory=list)
    derived: dict[str, Any] = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------- metadata
    @property
    def meta(self) -> dict[str, str]:
        """The recording's ``touchup`` metadata (empty if unknown)."""
        m = (self.recording or {}).get("metadata") or {}
        return {str(k): str(v) for k, v in m.items()}

    @property
    def tolerance_mm(self) -> float | None:
        """The accuracy the run had to reach (mm): run.json's ``tolerance_mm`` (the
        ``--tolerance-mm`` the run was given), else the recording's ``tolerance_mm`` key."""
        from pipeline.accuracy.verdict import tolerance_from_metadata

        given = tolerance_from_metadata(self.run)
        return given if given is not None else tolerance_from_metadata(self.meta)

    @property
    def tolerance_source(self) -> str:
        """Where :attr:`tolerance_mm` came from, in words ('' without a tolerance)."""
        from pipeline.accuracy.verdict import tolerance_from_metadata

        if tolerance_from_metadata(self.run) is not None:
            return "given on the command line, --tolerance-mm"
        if tolerance_from_metadata(self.meta) is not None:
            return "the recording's tolerance_mm metadata key"
        return ""

    @property
    def joint_names(self) -> list[str]:
        names = (self.recording or {}).get("joint_names")
        if names:
            return [str(n) for n in names]
        chain = self.nominal_chain() or self.calibrated_chain()
        return chain.joint_names if chain is not None else []

    @property
    def base_link(self) -> str | None:
        """From recording.json, else the root link of calibrated.urdf."""
        r = self.recording or {}
        name = r.get("base_link") or self.meta.get("base_link")
        if name:
            return str(name)
        robot = self._calibrated_robot()
        if robot is None:
            return None
        children = {j.child for j in robot.joints.values()}
        roots = [j.parent for j in robot.joints.values() if j.parent not in children]
        return roots[0] if roots else None

    @property
    def flange_link(self) -> str | None:
        """From recording.json, else the link calibrated.urdf fixes the virtual pin to."""
        r = self.recording or {}
        name = r.get("flange_link") or self.meta.get("flange_link")
        if name:
            return str(name)
        robot = self._calibrated_robot()
        if robot is None:
            return None
        for j in robot.joints.values():
            if j.child == PIN_LINK:
                return str(j.parent)
        return None

    def _calibrated_robot(self) -> RobotDescription | None:
        if not self.calibrated_urdf:
            return None
        try:
            return parse_urdf(self.calibrated_urdf)
        except Exception:  # noqa: BLE001 - shown as "not available"
            return None

    def robot_name(self) -> str:
        for xml in ((self.recording or {}).get("urdf"), self.calibrated_urdf):
            if xml:
                try:
                    return parse_urdf(xml).name or "robot"
                except Exception:  # noqa: BLE001 - a name is cosmetic
                    continue
        return "unknown robot"

    def recording_path(self) -> Path | None:
        """The recording (a file, or a rosbag2 directory), if recording.json names one that
        still exists."""
        p = (self.recording or {}).get("path")
        if not p:
            return None
        path = Path(p)
        # a relative path is as given on the command line: try the working folder, then
        # the run folder
        for cand in (path, self.run_dir / path) if not path.is_absolute() else (path,):
            if cand.is_file() or cand.is_dir():
                return cand.resolve()
        return None

    # --------------------------------------------------------------- chains
    def nominal_chain(self) -> Chain | None:
        xml = (self.recording or {}).get("urdf")
        if not xml or not self.base_link or not self.flange_link:
            return None
        try:
            return load_chain(xml, self.base_link, self.flange_link)
        except Exception:  # noqa: BLE001 - shown as "not available"
            return None

    def calibrated_chain(self) -> Chain | None:
        """Base to ``virtual_pin`` (or to the flange if the pin link is absent)."""
        if not self.calibrated_urdf or not self.base_link:
            return None
        try:
            robot = parse_urdf(self.calibrated_urdf)
        except Exception:  # noqa: BLE001
            return None
        for tip in (PIN_LINK, self.flange_link):
            if tip is None:
                continue
            try:
                return load_chain(robot, self.base_link, tip)
            except Exception:  # noqa: BLE001
                continue
        return None

    def p_flange_pin(self) -> np.ndarray | None:
        """Virtual-pin point in the flange frame, (3,) m, from calibrated.urdf."""
        ch = self.calibrated_chain()
        if ch is None or ch.tip_link != PIN_LINK:
            return None
        j = ch.joints[-1]
        return np.asarray(j.T_parent_joint[:3, 3], dtype=float)

    # ------------------------------------------------------------ touch-ups
    def touchup_table(self) -> pd.DataFrame | None:
        """Inliers (touch-ups + verdict) if present, else touch-ups with every row an inlier.

        Made once per load (a dozen sections ask for it) and handed out as a copy."""
        if "touchup_table" not in self.derived:
            self.derived["touchup_table"] = self._touchup_table()
        df = self.derived["touchup_table"]
        return None if df is None else df.copy()

    def _touchup_table(self) -> pd.DataFrame | None:
        if self.inliers is not None:
            df = self.inliers.copy()
            if self.touchups is not None and "touchup_id" in self.touchups:
                # bring back the extraction columns (frames, e_T history, ...) inliers leave out
                more = [c for c in self.touchups.columns if c not in df.columns]
                if more:
                    df = df.merge(self.touchups[["touchup_id", *more]], on="touchup_id", how="left")
        elif self.touchups is not None:
            df = self.touchups.copy()
            df["inlier"] = df.get("converged", True)
            df["reason"] = np.where(df["inlier"], "", "not converged")
        else:
            return None
        if "reason" not in df:
            df["reason"] = ""
        df["reason"] = df["reason"].fillna("").astype(str)
        return df.sort_values("touchup_id").reset_index(drop=True)

    def joint_matrix(self, df: pd.DataFrame) -> np.ndarray | None:
        """``(N, n)`` joint vectors of a touch-up table, in chain order."""
        names = self.joint_names
        if not names or any(n not in df.columns for n in names):
            return None
        return df[names].to_numpy(dtype=float)

    def date(self) -> str:
        """UTC date of the recording, from its stamps (never the wall clock)."""
        stamps: list[int] = []
        for df, col in (
            (self.frames, "stamp_ns"),
            (self.touchups, "stamp_ns"),
            (self.inliers, "stamp_ns"),
        ):
            if df is not None and col in df and len(df):
                s = pd.to_numeric(df[col], errors="coerce").dropna()
                s = s[s > 0]
                if len(s):
                    stamps.append(int(s.min()))
        if not stamps:
            return "unknown"
        t = pd.Timestamp(min(stamps), unit="ns", tz="UTC")
        return t.strftime("%Y-%m-%d %H:%M UTC")


def _read_parquet(path: Path, name: str) -> pd.DataFrame:
    if (SCHEMA_DIR / f"{name}.json").exists():
        try:
            return read_artefact(path, name)
        except Exception:  # noqa: BLE001 - an older/newer schema: still show what is there
            pass
    return pq.read_table(path).to_pandas()


def load_run(run_dir: Path) -> RunData:
    """Read every artefact of a run folder that exists (see :class:`RunData`)."""
    run_dir = Path(run_dir)
    data = RunData(run_dir=run_dir)
    for name, fname in PARQUET.items():
        p = run_dir / fname
        if p.exists():
            try:
                setattr(data, name, _read_parquet(p, name))
            except Exception as exc:  # noqa: BLE001
                data.problems.append(f"{fname}: unreadable ({type(exc).__name__}: {exc})"[:200])
    for name, fname in JSONS.items():
        p = run_dir / fname
        if p.exists():
            try:
                obj = json.loads(p.read_text())
                setattr(data, name, obj if isinstance(obj, dict) else {"value": obj})
            except Exception as exc:  # noqa: BLE001
                data.problems.append(f"{fname}: unreadable ({type(exc).__name__}: {exc})"[:200])
    p = run_dir / TEXTS["calibrated_urdf"]
    if p.exists():
        data.calibrated_urdf = p.read_text()
    return data


def artefact_hashes(run_dir: Path) -> dict[str, str]:
    """``{file name: content hash}`` of the report's input files present in ``run_dir``."""
    return {f: file_hash(run_dir / f) for f in INPUT_FILES if (run_dir / f).is_file()}


def run_uuid(run_dir: Path) -> str:
    """Deterministic id of a run folder's content: a UUID from its artefact hashes."""
    blob = json.dumps(artefact_hashes(Path(run_dir)), sort_keys=True).encode()
    return str(uuid.UUID(bytes=hashlib.sha256(blob).digest()[:16], version=5))


# ---------------------------------------------------------------- geometry


# ---------------------------------------------------------------- accuracy


# ------------------------------------------------------- frames / touch-ups
