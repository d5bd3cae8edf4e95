"""A robot's history: the same robot re-recorded with new poses, events between recordings.

The auditing benchmark and tests (``vtcal audit``, :mod:`pipeline.audit`) need
many recordings of one physical robot whose changes are known. This module makes
them at the touch-up level (the converged joint vectors a recording yields after
ingest, touch-up extraction and outlier rejection), fast enough for hundreds:

* **The robot** = nominal URDF + seeded deviations (the simulator's magnitudes,
  :func:`pipeline.accuracy.evaluate.random_deviations`), a virtual pin ``p_flange_pin``
  (the camera's mount, seeded), a base pose ``T_world_base`` and targets fixed
  in the cell ``p_world_target`` (K, 3).
* **A recording** touches every target ``per_target`` times from new joint
  vectors: a seed configuration per target with every joint moved by up to
  ``spread_rad``, pulled onto the target by Gauss-Newton on the true pin
  position (:func:`pipeline.accuracy.evaluate.solve_pin_ik`), then the pin misses the
  target by ``N(0, noise_pin_m^2)`` per axis and the encoders read the joints
  with ``N(0, noise_q_rad^2)`` (the noise of ``benchmarks/bench_identify.py``)::

      T_world_base T_base_flange(q_i; true) p_flange_pin = p_world_target[k] + e_i   (H1)

* **Events between recordings** (:class:`Event`), applied to the true robot:

  ========================  =================================================
  ``joint_offset`` (joint)  the joint's zero turned by ``size`` rad (``dq0``)
  ``link_length`` (joint)   the joint's origin moved ``size`` m along its nominal
                            offset (the length of the link before the joint)
  ``bent_link`` (joint)     the joint's origin turned by ``size`` rad about an
                            axis normal to the joint axis
  ``thermal``               every link offset scaled by ``1 + size`` (growth)
  ``camera``                the camera remounted: the pin moved ``size`` m in a
                            seeded direction
  ``base``                  the base moved ``size`` m in a seeded horizontal
                            direction and turned ``size / 1 m`` rad about z
  ========================  =================================================

The truth of each recording (deviations, pin, base pose, the event before it) is
kept beside it (:class:`HistoryRecording`); :func:`write_history` writes each as
a folder ``vtcal audit`` reads like a run folder: ``inliers.parquet``,
``recording.json`` (the nominal URDF, the chain ends, the metadata with
``robot_id``) and ``truth.json``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_positions,
    random_deviations,
    solve_pin_ik,
)
from pipeline.kinematics import load_chain
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64
from pipeline.robots import builtin_urdf

#: the kinds of event :func:`apply_event` knows
EVENT_KINDS = ("joint_offset", "link_length", "bent_link", "thermal", "camera", "base")
#: a nominal pin (flange frame, m): the standard cell's camera at 0.25 m
PIN = np.array([0.0167, -0.0101, 0.2524])
#: joint vectors the targets are touched about, per robot model (bench_identify's)
CENTRES = {
    "lrmate": np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32]),
    "ur5e": np.array([0.3, -1.2, 1.4, -1.6, -1.5, 0.2]),
    "iiwa7": np.full(7, 0.3),
}
#: one day between recordings
DAY_NS = 86_400 * 10**9
#: the first recording's stamp (2026-01-05 08:00 UTC)
START_NS = 1_767_600_000 * 10**9


@dataclasses.dataclass(frozen=True)
class Event:
    """A change of the physical robot between two recordings.

    Attributes
    ----------
    kind : one of :data:`EVENT_KINDS`
    size : rad (joint_offset, bent_link), m (link_length, camera, base), relative (thermal)
    joint : the joint it acts on (joint_offset, link_length, bent_link), else ``""``
    """

    kind: str
    size: float
    joint: str = ""

    def describe(self) -> str:
        """One line: what happened, in mm / deg."""
        if self.kind in ("joint_offset", "bent_link"):
            return f"{self.kind} {self.joint} {np.degrees(self.size):+.3f} deg"
        if self.kind == "thermal":
            return f"thermal growth {self.size * 1e6:+.0f} ppm"
        where = f" {self.joint}" if self.joint else ""
        return f"{self.kind}{where} {self.size * 1e3:+.3f} mm"


@dataclasses.dataclass
class RobotTruth:
    """The physical robot at one moment.

    Attributes
    ----------
    deviations : ``{joint: {"dxyz_m", "drpy_rad", "dq0_rad"}}`` (:func:`pipeline.accuracy.evaluate.perturbed_chain`)
    p_flange_pin : (3,) the virtual pin, flange frame (m)
    T_world_base : (4, 4) the base in the cell
    """

    deviations: dict[str, dict[str, Any]]
    p_flange_pin: F64
    T_world_base: F64

    def copy(self) -> RobotTruth:
        return RobotTruth(
            json.loads(json.dumps(self.deviations)),
            self.p_flange_pin.copy(),
            self.T_world_base.copy(),
        )


@dataclasses.dataclass
class HistoryRecording:
    """One recording of a history and its truth.

    Attributes
    ----------
    name : folder name (``ROBOT_ID-rNN``)
    robot_id : the physical robot
    robot : the robot model (builtin URDF name)
    stamp_ns : the recording's first stamp
    table : touch-up table (``schemas/inliers.json`` columns)
    truth : the robot when recorded
    event : the event between the previous recording and this one (None: none)
    true_chain : ``perturbed_chain(nominal, truth.deviations)``
    known_distances : the metadata key (``A:B=METRES``), '' without a bar
    """

    name: str
    robot_id: str
    robot: str
    stamp_ns: int
    table: pd.DataFrame
    truth: RobotTruth
    event: Event | None
    true_chain: Chain
    known_distances: str = ""


def _unit(v: F64) -> F64:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else np.array([1.0, 0.0, 0.0])


def apply_event(
    nominal: Chain, truth: RobotTruth, event: Event, rng: np.random.Generator
) -> RobotTruth:
    """The robot after ``event`` (a new :class:`RobotTruth`; ``truth`` unchanged)."""
    t = truth.copy()
    joints = {j.name: j for j in nominal.actuated}
    if event.kind in ("joint_offset", "link_length", "bent_link") and event.joint not in joints:
        raise ValueError(f"event {event.kind}: unknown joint {event.joint!r}")
    if event.kind == "joint_offset":
        t.deviations[event.joint]["dq0_rad"] += event.size
    elif event.kind == "link_length":
        d = _unit(np.asarray(joints[event.joint].T_parent_joint[:3, 3], dtype=float))
        dx = np.asarray(t.deviations[event.joint]["dxyz_m"]) + event.size * d
        t.deviations[event.joint]["dxyz_m"] = dx.tolist()
    elif event.kind == "bent_link":
        axis = np.asarray(joints[event.joint].axis, dtype=float)
        normal = _unit(np.cross(axis, rng.normal(size=3)))
        dr = np.asarray(t.deviations[event.joint]["drpy_rad"]) + event.size * normal
        t.deviations[event.joint]["drpy_rad"] = dr.tolist()
    elif event.kind == "thermal":
        for j in nominal.actuated:
            off = np.asarray(j.T_parent_joint[:3, 3], dtype=float)
            dx = np.asarray(t.deviations[j.name]["dxyz_m"]) + event.size * off
            t.deviations[j.name]["dxyz_m"] = dx.tolist()
    elif event.kind == "camera":
        t.p_flange_pin = t.p_flange_pin + event.size * _unit(rng.normal(size=3))
    elif event.kind == "base":
        a = rng.uniform(0, 2 * np.pi)
        yaw = event.size / 1.0
        c, s = np.cos(yaw), np.sin(yaw)
        T = np.eye(4)
        T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[:3, 3] = event.size * np.array([np.cos(a), np.sin(a), 0.0])
        t.T_world_base = T @ t.T_world_base
    else:
        raise ValueError(f"unknown event kind {event.kind!r} (one of {', '.join(EVENT_KINDS)})")
    return t


def touch_targets(
    chain: Chain,
    truth: RobotTruth,
    p_world_target: F64,
    q_centres: F64,
    per_target: int,
    rng: np.random.Generator,
    *,
    spread_rad: float = 0.35,
    noise_pin_m: float = 1e-5 / np.sqrt(3),
    noise_q_rad: float = 1e-6,
) -> pd.DataFrame:
    """One recording's touch-up table, (H1): new joint vectors on fixed targets.

    Parameters
    ----------
    chain : the true chain ; truth : its pin and base pose
    p_world_target : (K, 3) targets in the cell ; q_centres : (K, n) seed configurations
    per_target : touch-ups per target ; rng : the recording's generator

    Returns
    -------
    DataFrame with the ``schemas/inliers.json`` columns and one column per joint.
    """
    T_base_world = np.linalg.inv(truth.T_world_base)
    p_base = p_world_target @ T_base_world[:3, :3].T + T_base_world[:3, 3]
    n = chain.n_dof
    rows: list[dict[str, Any]] = []
    for k, (target, qc) in enumerate(zip(p_base, q_centres, strict=True)):
        got: list[F64] = []
        for _attempt in range(20):
            m = 2 * (per_target - len(got)) + 2
            miss = rng.normal(0.0, noise_pin_m, (m, 3))
            seeds = qc + rng.uniform(-spread_rad, spread_rad, (m, n))
            q, ok = solve_pin_ik(chain, truth.p_flange_pin, target + miss, seeds)
            got.extend(q[ok][: per_target - len(got)])
            if len(got) >= per_target:
                break
        if len(got) < per_target:
            raise RuntimeError(f"target {k}: only {len(got)} of {per_target} poses reach it")
        for q in got:
            q = q + rng.normal(0.0, noise_q_rad, n)
            rows.append({"target_id": k, **dict(zip(chain.joint_names, q, strict=True))})
    df = pd.DataFrame(rows)
    df.insert(0, "touchup_id", np.arange(len(df), dtype=np.int64))
    df.insert(2, "source_target_id", df["target_id"])
    for c in ("dx_flange", "dy_flange", "dz_flange"):
        df[c] = 0.0
    df["weight"] = 1.0
    df["converged"] = True
    df["stamp_ns"] = np.zeros(len(df), dtype=np.int64)
    df["inlier"] = True
    df["reason"] = ""
    df["note"] = ""
    for c in ("studentized", "leverage", "view_gx", "view_gy", "view_gz", "axis_lx", "axis_ly"):
        df[c] = np.nan
    for c in ("axis_lz", "axis_anisotropy", "pair_sxx", "pair_syy", "pair_szz", "pair_sxy"):
        df[c] = np.nan
    for c in ("pair_sxz", "pair_syz"):
        df[c] = np.nan
    return df


def make_history(
    robot_id: str,
    events: dict[int, Event] | None = None,
    *,
    robot: str = "lrmate",
    n_recordings: int = 6,
    seed: int = 0,
    n_targets: int = 3,
    per_target: int = 12,
    start_ns: int = START_NS,
    bar: bool = True,
    **noise: float,
) -> list[HistoryRecording]:
    """A robot's history: ``n_recordings`` recordings a day apart, ``events`` between them.

    Parameters
    ----------
    robot_id : the physical robot's name
    events : ``{i: Event}``: the event happens before recording ``i`` (1 .. n-1)
    robot : builtin robot model ; seed : the robot (deviations, pin, cell) and its recordings
    n_targets, per_target : touch-ups of each recording
    bar : the first and last target on a bar of known length (the standard cell's
        calibration bar: ``known_distances`` in the metadata, exact)
    noise : ``noise_pin_m``, ``noise_q_rad``, ``spread_rad`` of :func:`touch_targets`

    Returns
    -------
    list of :class:`HistoryRecording`, oldest first.
    """
    events = dict(events or {})
    bad = [i for i in events if not 1 <= i < n_recordings]
    if bad:
        raise ValueError(
            f"events at {bad}: an event happens before recording 1 .. {n_recordings - 1}"
        )
    urdf = builtin_urdf(robot)
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng([seed, 1])
    truth = RobotTruth(
        random_deviations(nominal, rng),
        PIN + rng.uniform(-2e-3, 2e-3, 3),
        np.eye(4),
    )
    chain = perturbed_chain(nominal, truth.deviations)
    n = nominal.n_dof
    lo = np.where(np.isfinite(nominal.lower), nominal.lower, -np.pi)
    hi = np.where(np.isfinite(nominal.upper), nominal.upper, np.pi)
    qc = np.clip(CENTRES[robot] + rng.uniform(-0.6, 0.6, (n_targets, n)), lo, hi)
    p_world_target = pin_positions(chain, truth.p_flange_pin, qc)
    bar_m = float(np.linalg.norm(p_world_target[-1] - p_world_target[0])) if bar else 0.0
    out = []
    for i in range(n_recordings):
        event = events.get(i)
        if event is not None:
            truth = apply_event(nominal, truth, event, np.random.default_rng([seed, 2, i]))
            chain = perturbed_chain(nominal, truth.deviations)
        table = touch_targets(
            chain,
            truth,
            p_world_target,
            qc,
            per_target,
            np.random.default_rng([seed, 3, i]),
            **noise,
        )
        stamp = start_ns + i * DAY_NS
        table["stamp_ns"] = stamp + 10**9 * np.arange(len(table), dtype=np.int64) * 20
        out.append(
            HistoryRecording(
                f"{robot_id}-r{i:02d}",
                robot_id,
                robot,
                stamp,
                table,
                truth.copy(),
                event,
                chain,
                f"0:{n_targets - 1}={bar_m:.9f}" if bar else "",
            )
        )
    return out


def truth_json(rec: HistoryRecording) -> dict[str, Any]:
    """The truth of one recording as JSON-able data."""
    return {
        "robot_id": rec.robot_id,
        "robot": rec.robot,
        "stamp_ns": rec.stamp_ns,
        "deviations": rec.truth.deviations,
        "p_flange_pin": rec.truth.p_flange_pin.tolist(),
        "T_world_base": rec.truth.T_world_base.tolist(),
        "event": None if rec.event is None else dataclasses.asdict(rec.event),
        "event_text": "" if rec.event is None else rec.event.describe(),
    }


def recording_json(rec: HistoryRecording) -> dict[str, Any]:
    """The ``recording.json`` a run folder of this recording would hold (the keys audit reads)."""
    urdf = builtin_urdf(rec.robot)
    return {
        "path": f"{rec.name}.mcap",
        "urdf": urdf,
        "metadata": {
            "robot_id": rec.robot_id,
            "base_link": "base_link",
            "flange_link": "flange",
            **({"known_distances": rec.known_distances} if rec.known_distances else {}),
        },
        "inferred": {},
        "joint_names": list(rec.true_chain.joint_names),
        "base_link": "base_link",
        "flange_link": "flange",
        "first_stamp_ns": rec.stamp_ns,
    }


def write_history(history: list[HistoryRecording], out: Path) -> list[Path]:
    """Write each recording as ``out/NAME/{inliers.parquet, recording.json, truth.json}``."""
    from pipeline.io.artefacts import write_artefact
    from pipeline.io.run_folder import RUN_FILES

    folders = []
    for rec in history:
        folder = Path(out) / rec.name
        folder.mkdir(parents=True, exist_ok=True)
        write_artefact(folder / RUN_FILES["inliers"], rec.table, "inliers", stage="history")
        (folder / RUN_FILES["recording"]).write_text(json.dumps(recording_json(rec), indent=1))
        (folder / "truth.json").write_text(json.dumps(truth_json(rec), indent=1))
        folders.append(folder)
    return folders
