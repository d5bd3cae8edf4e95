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
from pipeline.live.protocols import F64


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
    rows : (N,) the file's row of each pose (``0 .. N-1`` in the file's order;
        another order after :func:`in_travel_order`)
    """

    path: Path
    sha256: str
    target_ids: list[int]
    q: F64
    joint_names: list[str]
    rows: list[int] | None = None

    def __len__(self) -> int:
        return len(self.target_ids)

    def row(self, i: int) -> int:
        """The file's row of the ``i``-th pose visited."""
        return i if self.rows is None else self.rows[i]


#: the plan's visiting orders ``vtcal measure --order`` takes
ORDERS = ("plan", "travel")


def in_travel_order(plan: Plan) -> Plan:
    """The plan's poses in the order of shortest joint travel (``vtcal measure --order travel``).

    A large move at a common speed limit takes ``1.875 |q_a - q_b|_inf / v`` (the
    synchronised quintic move; at least a minimum duration) followed by a fixed
    settle time, so the order that minimises the summed joint travel
    ``sum |q_a - q_b|_inf`` minimises the cell's travel and settle time too: nearest
    neighbour then 2-opt (:func:`pipeline.plan.order.order_visits`), starting at the
    file's first pose, without a cost for changing target (the image Jacobian is kept
    per target, so going back to a target probes nothing). The order depends on the
    file alone, so a resumed run follows the same one.
    """
    from pipeline.plan.order import order_visits

    o = [int(k) for k in order_visits(plan.q, plan.target_ids, switch_cost=0.0)]
    return Plan(
        plan.path,
        plan.sha256,
        [plan.target_ids[k] for k in o],
        plan.q[o],
        plan.joint_names,
        [plan.row(k) for k in o],
    )


def joint_travel(plan: Plan, q_start: F64 | None = None) -> float:
    """Summed largest joint change of the plan's large moves (rad), from ``q_start`` if given."""
    q = plan.q if q_start is None else np.vstack([q_start, plan.q])
    return float(np.sum(np.max(np.abs(np.diff(q, axis=0)), axis=1))) if len(q) > 1 else 0.0


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
