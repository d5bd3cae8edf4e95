"""Everything the report and the Rerun recording show, read from a run folder only.

A run folder (``../shared/spec/outputs.md``) holds one artefact per stage. The
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
import math
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from pipeline.artefacts import SCHEMA_DIR, file_hash, read_artefact
from pipeline.catalog import RUN_FILES
from pipeline.kinematics.chain import Chain, fk_frames, load_chain
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
        from pipeline.verdict import tolerance_from_metadata

        given = tolerance_from_metadata(self.run)
        return given if given is not None else tolerance_from_metadata(self.meta)

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
        """The recording file, if recording.json names one that still exists."""
        p = (self.recording or {}).get("path")
        if not p:
            return None
        path = Path(p)
        # a relative path is as given on the command line: try the working folder, then
        # the run folder
        for cand in (path, self.run_dir / path) if not path.is_absolute() else (path,):
            if cand.is_file():
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
        """Inliers (touch-ups + verdict) if present, else touch-ups with every row an inlier."""
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


def skeleton_points(chain: Chain, q: np.ndarray) -> np.ndarray:
    """Joint-frame origins then the tip origin: ``(N, n + 2, 3)`` m, base origin first.

    ``[0, o_1, ..., o_n, o_tip]`` with ``o_k = T_base_joint_k[:3, 3]`` from
    :func:`pipeline.kinematics.chain.fk_frames`: the line strip a viewer draws as
    the robot's kinematic skeleton.
    """
    T_tip, T_joints = fk_frames(chain, np.atleast_2d(q))
    N = T_tip.shape[0]
    pts = np.concatenate(
        [np.zeros((N, 1, 3)), T_joints[:, :, :3, 3], T_tip[:, None, :3, 3]], axis=1
    )
    return pts


def chosen_model(data: RunData) -> str | None:
    """The error model the run reports (identify.json ``model``), if named."""
    idf = data.identify or {}
    m = idf.get("best_model") or idf.get("model")
    return str(m) if m else None


def for_model(data: RunData, df: pd.DataFrame | None) -> pd.DataFrame | None:
    """Rows of a per-model artefact for the reported model (all rows if it has no model column)."""
    if df is None or "model" not in df.columns or not len(df):
        return df
    m = chosen_model(data)
    models = [str(x) for x in pd.unique(df["model"])]
    pick = m if m in models else models[0]
    return df[df["model"].astype(str) == pick]


def target_positions(data: RunData) -> dict[int, np.ndarray]:
    """``{target_id: p_base_target (3,)}`` m from targets.parquet (reported model)."""
    df = for_model(data, data.targets)
    if df is None or not len(df):
        return {}
    cols = _first_cols(df, [("x", "y", "z"), ("x_m", "y_m", "z_m"), ("px", "py", "pz")])
    if cols is None or "target_id" not in df:
        return {}
    return {
        int(r["target_id"]): np.array([r[c] for c in cols], dtype=float) for _, r in df.iterrows()
    }


def _first_cols(df: pd.DataFrame, options: list[tuple[str, ...]]) -> tuple[str, ...] | None:
    for opt in options:
        if all(c in df.columns for c in opt):
            return opt
    return None


def pin_positions(data: RunData, df: pd.DataFrame) -> np.ndarray | None:
    """Calibrated virtual-pin positions ``(N, 3)`` m in the base frame at each row's ``q``.

    ``p_base_pin = T_base_pin(q)[:3, 3]`` with the chain of calibrated.urdf to
    ``virtual_pin``, the residual correction ``(dx, dy, dz)_flange`` added in the
    flange frame when present (``touchups.md``).
    """
    ch = data.calibrated_chain()
    q = data.joint_matrix(df)
    if ch is None or q is None or ch.tip_link != PIN_LINK:
        return None
    T = fk_frames(ch, q)[0]
    p = T[:, :3, 3].copy()
    d = _first_cols(df, [("dx_flange", "dy_flange", "dz_flange")])
    if d is not None:
        dfl = df[list(d)].to_numpy(dtype=float)
        dfl = np.nan_to_num(dfl)
        p += np.einsum("nij,nj->ni", T[:, :3, :3], dfl)
    return p


# ---------------------------------------------------------------- accuracy


@dataclass
class Figure:
    """One accuracy figure of the verdict: ``rms_mm`` and ``max_mm`` over ``n`` points."""

    label: str
    rms_mm: float | None
    max_mm: float | None
    n: int | None = None
    note: str = ""


def _stats_mm(norms_m: np.ndarray) -> tuple[float, float]:
    x = np.asarray(norms_m, dtype=float)
    x = x[np.isfinite(x)]
    if not len(x):
        return math.nan, math.nan
    return float(np.sqrt(np.mean(x * x)) * 1e3), float(np.max(x) * 1e3)


def residual_norms(df: pd.DataFrame) -> np.ndarray | None:
    """Residual lengths (m) of a residual table: a norm column or the norm of x/y/z columns."""
    for c in ("norm", "norm_m", "distance", "error_m", "residual_m", "r"):
        if c in df.columns:
            return df[c].to_numpy(dtype=float)
    cols = _first_cols(
        df,
        [("ex", "ey", "ez"), ("rx", "ry", "rz"), ("dx", "dy", "dz"), ("x", "y", "z"),
         ("ex_m", "ey_m", "ez_m"), ("rx_m", "ry_m", "rz_m")],
    )  # fmt: skip
    if cols is None:
        return None
    return np.linalg.norm(df[list(cols)].to_numpy(dtype=float), axis=1)


def residual_vectors(df: pd.DataFrame) -> np.ndarray | None:
    """Residual vectors ``(N, 3)`` m of a residual table, or None."""
    cols = _first_cols(
        df,
        [("ex", "ey", "ez"), ("rx", "ry", "rz"), ("dx", "dy", "dz"),
         ("ex_m", "ey_m", "ez_m"), ("rx_m", "ry_m", "rz_m")],
    )  # fmt: skip
    if cols is None:
        return None
    return df[list(cols)].to_numpy(dtype=float)


NOMINAL = "nominal"


def residual_groups(data: RunData) -> dict[str, pd.DataFrame]:
    """Residual rows of the used touch-ups, per model: ``nominal`` first, then the reported model.

    ``nominal`` is :func:`nominal_fit` (the nominal robot with its best pin and
    targets); the others come from residuals.parquet, one group per error model
    (rows with ``used``/``inlier`` false and rows without a residual left out).
    """
    out: dict[str, pd.DataFrame] = {}
    nom = nominal_fit(data)
    if nom is not None and len(nom):
        out[NOMINAL] = nom
    df = data.residuals
    if df is None or not len(df):
        return out
    for flag in ("used", "inlier"):
        if flag in df.columns:
            df = df[df[flag].astype(bool)]
    if "model" not in df.columns:
        out["calibrated"] = df
        return out
    models = [str(m) for m in pd.unique(df["model"])]
    chosen = chosen_model(data)
    if chosen in models:
        models.remove(chosen)
        models.insert(0, chosen)
    for m in models:
        g = df[df["model"].astype(str) == m]
        n = residual_norms(g)
        if n is not None and np.isfinite(n).any():
            out[m if m != NOMINAL else f"{m} (fitted)"] = g[np.isfinite(n)]
    return out


def _num(d: dict[str, Any], *keys: str) -> float | None:
    for k in keys:
        v = d.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            return float(v)
    return None


def _mm(d: dict[str, Any], what: str) -> float | None:
    """``d[what + "_mm"]``, else ``d[what + "_m"]`` or ``d[what]`` (metres) in mm."""
    v = _num(d, f"{what}_mm")
    if v is not None:
        return v
    v = _num(d, f"{what}_m", what)
    return v * 1e3 if v is not None else None


def accuracy_figures(data: RunData) -> list[Figure]:
    """The verdict's accuracy rows (mm), before and after, from whatever the run holds.

    Sources, in order: residuals.parquet (RMS and max of the residual lengths
    per model label), identify.json (``predicted`` figures and any
    ``rms_*``/``max_*`` entries), crossval.parquet (held-out residuals per model).
    """
    figs: list[Figure] = []
    for label, g in residual_groups(data).items():
        n = residual_norms(g)
        if n is None:
            continue
        rms, mx = _stats_mm(n)
        if label == NOMINAL:
            text = "fit residual, nominal robot (best pin and targets)"
        else:
            text = f"fit residual, model {label}"
        figs.append(Figure(text, rms, mx, len(n)))
    idf = data.identify or {}
    for stage in ("before", "after", "nominal", "calibrated"):
        sub = idf.get(stage)
        if isinstance(sub, dict):
            r_mm, m_mm = _mm(sub, "rms"), _mm(sub, "max")
            if r_mm is not None or m_mm is not None:
                figs.append(Figure(f"identify: {stage}", r_mm, m_mm))
    scale_held = bool(idf.get("scale_held", True))
    for kind, text in (
        ("shape", "predicted shape accuracy (similarity registration)"),
        ("absolute", "predicted absolute accuracy (rigid registration)"),
        ("", "predicted pin error (from the parameter covariance)"),
    ):
        key = f"predicted_{kind}_" if kind else "predicted_"
        p_rms, p_max = _num(idf, key + "rms_mm"), _num(idf, key + "max_mm")
        if p_rms is None and p_max is None:
            continue
        note = ""
        if kind == "absolute" and scale_held:
            note = "not reachable: no known distance, the scale was held at nominal"
        figs.append(Figure(text, p_rms, p_max, note=note))
    pred = idf.get("predicted")
    if isinstance(pred, dict):
        figs.append(
            Figure("predicted (from parameter covariance)", _mm(pred, "rms"), _mm(pred, "max"))
        )
    for row in crossval_summary(data):
        for scheme, text in (("kfold", "k-fold"), ("loto", "leave one target out")):
            if row[f"{scheme}_n"]:
                figs.append(
                    Figure(
                        f"cross-validated ({text}), model {row['model']}",
                        row[f"{scheme}_rms_mm"],
                        row[f"{scheme}_max_mm"],
                        row[f"{scheme}_n"],
                    )
                )
    return figs


def crossval_summary(data: RunData) -> list[dict[str, Any]]:
    """Held-out RMS/max (mm) per error model and scheme from crossval.parquet.

    Returns one dict per model: ``model``, and for each scheme ``s`` in
    (``kfold``, ``loto``) ``s_rms_mm``, ``s_max_mm``, ``s_n`` (scored touch-ups)
    and ``s_unscored`` (rows with a status). Without a ``scheme`` column every
    row counts as ``kfold``; residual lengths come from ``error_mm`` or from the
    residual vector columns (m).
    """
    df = data.crossval
    if df is None or not len(df):
        return []
    key = next((c for c in ("model", "error_model", "name") if c in df.columns), None)
    groups = list(df.groupby(key, sort=False)) if key else [("model", df)]
    out = []
    for name, g in groups:
        row: dict[str, Any] = {"model": str(name)}
        for scheme in ("kfold", "loto"):
            if "scheme" in g.columns:
                gs = g[g["scheme"] == scheme]
            else:
                gs = g if scheme == "kfold" else g.iloc[:0]
            if "error_mm" in gs.columns:
                e = gs["error_mm"].to_numpy(dtype=float) / 1e3
            else:
                n = residual_norms(gs)
                e = n if n is not None else np.full(len(gs), np.nan)
            ok = np.isfinite(e)
            if "status" in gs.columns:
                ok &= (gs["status"].fillna("").astype(str) == "").to_numpy()
            rms, mx = _stats_mm(e[ok]) if ok.any() else (None, None)
            row[f"{scheme}_rms_mm"] = rms
            row[f"{scheme}_max_mm"] = mx
            row[f"{scheme}_n"] = int(ok.sum())
            row[f"{scheme}_unscored"] = int(len(gs) - ok.sum())
        out.append(row)
    return out


# ------------------------------------------------------- frames / touch-ups

FRAME_COLS = ("frame", "frame_index", "image_index", "index")


def frame_col(df: pd.DataFrame | None) -> str | None:
    """Name of the frame-index column of frames/detections (tolerant)."""
    if df is None:
        return None
    return next((c for c in FRAME_COLS if c in df.columns), None)


def designated(data: RunData) -> tuple[float, float, float] | None:
    """``(u0, v0, s0)`` px from the recording metadata, or None."""
    m = data.meta
    try:
        return (
            float(m["designated_u"]),
            float(m["designated_v"]),
            float(m.get("designated_size_px", "nan")),
        )
    except (KeyError, ValueError):
        return None


def touchup_frames(data: RunData) -> dict[int, list[int]]:
    """``{touchup_id: [frame index, ...]}`` of each touch-up's captures, in order.

    From a ``touchup_id`` column of frames.parquet, else list-valued ``frames``
    columns of the touch-up table, else a single ``frame``/``last_frame`` column,
    else by matching the touch-up's ``stamp_ns`` to a frame's stamp.
    """
    out: dict[int, list[int]] = {}
    fr = data.frames
    fc = frame_col(fr)
    if fr is not None and fc is not None and "touchup_id" in fr.columns:
        sub = fr[
            pd.notna(fr["touchup_id"]) & (pd.to_numeric(fr["touchup_id"], errors="coerce") >= 0)
        ]
        for tid, g in sub.groupby("touchup_id"):
            out[int(str(tid))] = [int(i) for i in g.sort_values(fc)[fc]]
        if out:
            return out
    tu = data.touchup_table()
    if tu is None:
        return out
    for c in ("frames", "frame_indices", "capture_frames"):
        if c in tu.columns:
            for _, r in tu.iterrows():
                v = r[c]
                if v is not None and len(v):
                    out[int(r["touchup_id"])] = [int(i) for i in v]
            return out
    for c in ("last_frame", "frame", "frame_index", "final_frame"):
        if c in tu.columns:
            for _, r in tu.iterrows():
                if pd.notna(r[c]) and int(r[c]) >= 0:
                    out[int(r["touchup_id"])] = [int(r[c])]
            return out
    if fr is not None and fc is not None and "stamp_ns" in fr.columns and "stamp_ns" in tu.columns:
        by_stamp = dict(zip(fr["stamp_ns"].astype("int64"), fr[fc].astype("int64"), strict=False))
        for _, r in tu.iterrows():
            i = by_stamp.get(int(r["stamp_ns"]))
            if i is not None:
                out[int(r["touchup_id"])] = [int(i)]
    return out


def detection_ellipse(data: RunData, frame: int) -> tuple[float, float, float, float, float] | None:
    """``(u, v, s, s_minor, angle)`` of the detection in a frame, or None."""
    det = data.detections
    fc = frame_col(det)
    if det is None or fc is None or not {"u", "v", "s"} <= set(det.columns):
        return None
    rows = det[det[fc] == frame]
    if not len(rows):
        return None
    r = rows.iloc[0]
    if not np.isfinite(float(r["u"])):
        return None
    sm = float(r["s_minor"]) if "s_minor" in r else float(r["s"])
    ang = float(r["angle"]) if "angle" in r else 0.0
    return float(r["u"]), float(r["v"]), float(r["s"]), sm, ang


def convergence_traces(data: RunData) -> dict[int, np.ndarray]:
    """``{touchup_id: (k, 3)}`` e_T history ``(du, dv, ds)`` px of each touch-up.

    From the list-valued history columns of the touch-up table when it has them
    (``e_u_history``, ``e_v_history``, ``e_s_history``), else rebuilt from
    the detections of each touch-up's captures: ``du = u - u0``, ``dv = v - v0``,
    ``ds = s - s0`` against the designated values (recording.md).
    """
    tu = data.touchup_table()
    out: dict[int, np.ndarray] = {}
    if tu is not None:
        for names in (
            ("e_u_history", "e_v_history", "e_s_history"),
            ("e_u_px", "e_v_px", "e_s_px"),
            ("du_px", "dv_px", "ds_px"),
        ):
            if all(n in tu.columns for n in names):
                for _, r in tu.iterrows():
                    cols = [
                        np.asarray(r[n] if r[n] is not None else [], dtype=float) for n in names
                    ]
                    k = min(len(c) for c in cols)
                    if k:
                        out[int(r["touchup_id"])] = np.stack([c[:k] for c in cols], axis=1)
                return out
    d0 = designated(data)
    det = data.detections
    fc = frame_col(det)
    if d0 is None or det is None or fc is None or not {"u", "v", "s"} <= set(det.columns):
        return out
    det_i = det.set_index(fc)
    for tid, frames in touchup_frames(data).items():
        if len(frames) < 2:
            continue
        rows = det_i.reindex(frames)
        e = np.stack(
            [
                rows["u"].to_numpy(float) - d0[0],
                rows["v"].to_numpy(float) - d0[1],
                rows["s"].to_numpy(float) - d0[2],
            ],
            axis=1,
        )
        e = e[np.all(np.isfinite(e), axis=1)]
        if len(e):
            out[tid] = e
    return out


def nominal_fit(data: RunData) -> pd.DataFrame | None:
    """Residuals of the nominal robot with its best virtual pin and target positions.

    The "before" of the verdict: with the nominal kinematics fixed, the pin
    point ``p`` (flange frame) and the target centres ``c_k`` (base frame) that
    best explain the used touch-ups solve a linear least-squares problem,

        R_i (p + d_i) + t_i = c_{k(i)}   =>   [R_i, -E_k] [p; c] = -(t_i + R_i d_i),

    with ``(R_i, t_i) = T_base_flange(q_i)`` and ``d_i`` the residual correction
    ``(dx, dy, dz)_flange``. Its residuals are what the nominal model leaves
    before any kinematic parameter is touched. Returns a table ``touchup_id,
    target_id, rx, ry, rz, norm`` (m) or None when inputs are missing.

    No artefact holds these residuals (identify.json keeps only each model's
    initial RMS), so they are computed here, once per loaded run folder
    (``data.derived``): the verdict, the residual plots and the accuracy table share them.
    """
    if "nominal_fit" not in data.derived:
        data.derived["nominal_fit"] = _nominal_fit(data)
    got: pd.DataFrame | None = data.derived["nominal_fit"]
    return got


def _nominal_fit(data: RunData) -> pd.DataFrame | None:
    """:func:`nominal_fit`, computed."""
    chain = data.nominal_chain()
    tu = data.touchup_table()
    if chain is None or tu is None or "target_id" not in tu:
        return None
    if "inlier" in tu:
        tu = tu[tu["inlier"].astype(bool)]
    q = data.joint_matrix(tu)
    if q is None or len(tu) < 2:
        return None
    from pipeline.evaluate import fit_pin_and_targets

    d = np.zeros((len(tu), 3))
    cols = _first_cols(tu, [("dx_flange", "dy_flange", "dz_flange")])
    if cols is not None:
        d = np.nan_to_num(tu[list(cols)].to_numpy(dtype=float))
    ids = tu["target_id"].to_numpy()
    uniq = list(pd.unique(ids))
    tk = np.array([uniq.index(i) for i in ids], dtype=np.int64)
    _, _, r = fit_pin_and_targets(chain, q, d, tk, len(uniq))
    return pd.DataFrame(
        {
            "touchup_id": tu["touchup_id"].to_numpy(),
            "target_id": ids,
            "rx": r[:, 0],
            "ry": r[:, 1],
            "rz": r[:, 2],
            "norm": np.linalg.norm(r, axis=1),
        }
    )
