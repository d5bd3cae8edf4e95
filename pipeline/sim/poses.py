"""The planned measuring poses of a simulated session: from a plan file or a built-in spread."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import BadInput
from pipeline.kinematics.chain import fk
from pipeline.kinematics.se3 import F64, matrix_from_axis_angle, transform_from
from pipeline.sim.cell import Cell, rot_between
from pipeline.sim.robot import solve_ik
from pipeline.sim.scenario import Scenario


def measuring_poses(sc: Scenario, cell: Cell, rng: np.random.Generator) -> list[tuple[int, F64]]:
    """Planned ``(target_id, q)`` list: from the plan file or a built-in spread.

    Built-in: per target, view directions ``w`` (target -> camera) in a cone
    of ``cone_half_angle_deg`` about the plate normal (sunflower spread in
    solid angle) and a roll about ``w`` in ``+-roll_range_deg``; the flange
    pose puts a *believed* pin (the true one + a few mm, as taught by hand)
    on the target with the camera looking along ``-w``, solved by nominal IK
    within the joint limits (a draw that fails is replaced by another).
    """
    if sc.poses.plan:
        return _poses_from_plan(sc, cell)
    out: list[tuple[int, F64]] = []
    chain = cell.nominal
    R_fc = cell.T_flange_camera[:3, :3]
    p_vt_believed = cell.p_vt_flange + rng.normal(0.0, 0.002, 3)
    cone = np.deg2rad(sc.poses.cone_half_angle_deg)
    roll_range = np.deg2rad(sc.poses.roll_range_deg)
    K = sc.poses.per_target
    T_home = fk(chain, cell.home)
    az_home = np.arctan2(T_home[1, 3], T_home[0, 3])
    for tg in cell.targets:
        # reference orientation: the home flange orientation turned about the base z axis
        # towards the target (keeps the wrist near its home winding)
        az = np.arctan2(tg.centre[1], tg.centre[0]) - az_home
        R_ref = matrix_from_axis_angle([0.0, 0.0, 1.0], az) @ T_home[:3, :3]
        R_ref_cam = R_ref @ R_fc
        q_prev = cell.home.copy()
        phase = rng.uniform(0, 2 * np.pi)
        found = 0
        attempt = 0
        while found < K and attempt < 40 * K:
            k = found if attempt < K else int(rng.integers(0, K))
            theta = cone * np.sqrt((k + 0.5) / K) if attempt < 2 * K else rng.uniform(0, cone)
            phi = phase + k * 2.399963229728653 + (0.0 if attempt < K else rng.uniform(0, 6.3))
            roll = rng.uniform(-roll_range, roll_range)
            attempt += 1
            n = tg.normal
            e1 = tg.R[:, 0]
            e2 = tg.R[:, 1]
            w = np.cos(theta) * n + np.sin(theta) * (np.cos(phi) * e1 + np.sin(phi) * e2)
            R_cam = matrix_from_axis_angle(w, roll) @ rot_between(R_ref_cam[:, 2], -w) @ R_ref_cam
            R_flange = R_cam @ R_fc.T
            p_flange = tg.centre - R_flange @ p_vt_believed
            T_goal = transform_from(R_flange, p_flange)
            seeds = [q_prev, cell.home] + [
                rng.uniform(np.maximum(chain.lower, -np.pi), np.minimum(chain.upper, np.pi))
                for _ in range(3)
            ]
            for seed in seeds:
                q, ok = solve_ik(chain, T_goal, seed, q_rest=cell.home, max_iter=150)
                if ok:
                    out.append((tg.id, q))
                    q_prev = q
                    found += 1
                    break
        if found < K:
            raise BadInput(
                f"scenario {sc.name}: only {found} of {K} measuring poses of target {tg.id} "
                f"at {np.round(tg.centre, 3).tolist()} are reachable; move the targets "
                "([targets] centre_m) or narrow [poses] cone_half_angle_deg"
            )
    return out


#: a plan made for a pin farther than this from the cell's starts its touch-ups too far off:
#: a third of the half field of view of the standard cells at their stand-off (17 mm off
#: worked in docs/planner.md's example, 69 mm (the planner's default pin) lost 34 of 36)
MAX_PLAN_PIN_OFFSET_M = 0.03


def _check_plan_pin(path: Path, cell: Cell) -> None:
    """Refuse a plan made (``vtcal plan --pin``) for another virtual pin than this cell's.

    The planner puts the pin it was given on each target; the cell's camera puts its
    own pin there. Farther apart than ``MAX_PLAN_PIN_OFFSET_M``, the touch-ups start
    centimetres off and most are lost.
    """
    import json

    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
        planned = json.loads(meta.get(b"vtcal.plan", b"{}")).get("config", {}).get("p_flange_pin")
    except (OSError, ValueError):
        return
    if planned is None:
        return  # a plan written by hand: nothing to compare
    off = float(np.linalg.norm(np.asarray(planned, dtype=float) - cell.p_vt_flange))
    if off > MAX_PLAN_PIN_OFFSET_M:
        want = ",".join(f"{v:.3f}" for v in cell.p_vt_flange)
        raise BadInput(
            f"{path}: planned for a virtual pin at {[round(float(v), 4) for v in planned]} m in "
            f"the flange frame, but this scenario's camera puts it at "
            f"{[round(float(v), 4) for v in cell.p_vt_flange]} ({1e3 * off:.0f} mm away): every "
            f"pose would miss its target; plan with --pin {want}"
        )


def _poses_from_plan(sc: Scenario, cell: Cell) -> list[tuple[int, F64]]:
    import pandas as pd

    path = Path(str(sc.poses.plan))
    if not path.exists() and not path.is_absolute():
        path = Path(sc.base_dir) / path
    if not path.exists():
        raise BadInput(f"{sc.poses.plan}: plan file not found")
    try:
        df = pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is bad input
        raise BadInput(f"{path}: not a readable Parquet plan ({exc})") from exc
    names = cell.nominal.joint_names
    missing = [c for c in ["target_id", *names] if c not in df.columns]
    if missing:
        raise BadInput(f"{path}: plan lacks columns {missing} (needs target_id and {names})")
    _check_plan_pin(path, cell)
    ids = {t.id for t in cell.targets}
    out = []
    for row in df.itertuples(index=False):
        raw = getattr(row, "target_id")  # noqa: B009
        try:
            tid = int(raw)
        except (TypeError, ValueError):
            raise BadInput(f"{path}: target_id {raw!r} is not an integer target id") from None
        if tid not in ids:
            raise BadInput(f"{path}: target_id {tid} not in the scenario (0..{len(ids) - 1})")
        q = np.array([float(getattr(row, n)) for n in names])
        out.append((tid, q))
    return out
