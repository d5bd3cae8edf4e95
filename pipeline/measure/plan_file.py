"""The plan ``vtcal measure`` follows, read from ``vtcal plan``'s Parquet, checked before any move.

A plan is one row per measuring pose: ``target_id`` and one column per joint
of the robot (named as in the nominal URDF; rad, or m for a prismatic joint).
Every pose is checked against the nominal URDF's joint limits before the arm
moves at all: one pose out of its limits refuses the whole run.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.errors import BadInput, VtcalError
from pipeline.kinematics.urdf import parse_urdf
from pipeline.measure.protocols import F64


class PlanRefused(VtcalError):
    """A planned pose the robot must not be sent to (outside its joint limits). Exit code 3."""

    exit_code = 3


@dataclass(frozen=True)
class Plan:
    """Measuring poses in order.

    Attributes
    ----------
    path : the file
    sha256 : hash of its bytes (a resumed run must follow the same plan)
    target_ids : (N,) int
    q : (N, n) joint positions, columns in ``joint_names`` order
    joint_names : the robot's joint names
    """

    path: Path
    sha256: str
    target_ids: list[int]
    q: F64
    joint_names: list[str]

    def __len__(self) -> int:
        return len(self.target_ids)


def read_plan(path: Path, joint_names: list[str]) -> Plan:
    """Read ``path`` for a robot with ``joint_names``.

    Raises
    ------
    BadInput
        Missing or unreadable file, missing columns, non-integer target ids,
        non-finite joint values, no rows.
    """
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise BadInput(f"{path}: plan file not found")
    data = path.read_bytes()
    try:
        df = pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001 - any reader failure is bad input
        raise BadInput(f"{path}: not a readable Parquet plan ({exc})") from None
    missing = [c for c in ["target_id", *joint_names] if c not in df.columns]
    if missing:
        raise BadInput(f"{path}: plan lacks columns {missing} (needs target_id and {joint_names})")
    if len(df) == 0:
        raise BadInput(f"{path}: plan has no poses")
    try:
        ids = [int(v) for v in df["target_id"]]
    except (TypeError, ValueError):
        raise BadInput(f"{path}: target_id must be integers") from None
    q = df[joint_names].to_numpy(dtype=np.float64)
    bad = ~np.isfinite(q)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise BadInput(f"{path}: row {r}: {joint_names[c]} is {q[r, c]}")
    return Plan(path, hashlib.sha256(data).hexdigest(), ids, q, list(joint_names))


def check_limits(plan: Plan, urdf: str, margin_rad: float = 0.0) -> None:
    """Refuse the plan if a pose is outside the nominal URDF's joint limits (less ``margin_rad``).

    Raises
    ------
    PlanRefused
        Naming the first offending pose, joint, value and limits (degrees for
        revolute joints).
    BadInput
        A plan joint that the URDF does not have.
    """
    robot = parse_urdf(urdf)
    for c, name in enumerate(plan.joint_names):
        j = robot.joints.get(name)
        if j is None:
            raise BadInput(f"{plan.path}: joint {name!r} is not in the nominal URDF")
        lo, hi = j.lower + margin_rad, j.upper - margin_rad
        out = np.flatnonzero((plan.q[:, c] < lo) | (plan.q[:, c] > hi))
        if out.size:
            r = int(out[0])
            v = float(plan.q[r, c])
            deg = j.type != "prismatic"
            f = np.degrees if deg else (lambda x: x)
            unit = "deg" if deg else "m"
            raise PlanRefused(
                f"{plan.path}: pose {r} (target {plan.target_ids[r]}): {name} = {f(v):.2f} {unit} "
                f"outside the nominal URDF's limits [{f(j.lower):.2f}, {f(j.upper):.2f}] {unit}"
                f"{f' less a {np.degrees(margin_rad):.1f} deg margin' if margin_rad else ''}; "
                f"{out.size} pose(s) out of limits, nothing was moved"
            )
