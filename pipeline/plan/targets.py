"""The planner's targets file: approximate target centres and plate normals.

CSV with a header and the columns ``target_id, x, y, z, nx, ny, nz``: the
approximate centre of each target circle and the normal of its plate (the
side the camera looks from), both in the robot base frame, metres. The
normal need not be unit length. Extra columns are ignored.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64

COLUMNS = ("target_id", "x", "y", "z", "nx", "ny", "nz")


@dataclass(frozen=True)
class PlanTargets:
    """Targets the planner places measuring poses on.

    Attributes
    ----------
    ids : (K,) int64 target ids, unique
    centres : (K, 3) approximate centres, base frame, m
    normals : (K, 3) unit plate normals, base frame
    """

    ids: np.ndarray
    centres: F64
    normals: F64

    def __len__(self) -> int:
        return len(self.ids)


def targets_from_frame(df: pd.DataFrame, where: str = "targets") -> PlanTargets:
    """Validate a targets table (see module docstring) into :class:`PlanTargets`.

    Raises
    ------
    BadInput
        Missing columns, no rows, non-integer or repeated ids, non-finite values
        or a zero normal; the message names ``where`` and the offending row.
    """
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise BadInput(f"{where}: missing column(s) {missing} (needs {', '.join(COLUMNS)})")
    if len(df) == 0:
        raise BadInput(f"{where}: no targets")
    ids = []
    for raw in df["target_id"].tolist():
        try:
            f = float(raw)
        except (TypeError, ValueError):
            raise BadInput(f"{where}: target_id {raw!r} is not an integer") from None
        if not np.isfinite(f) or not f.is_integer():
            raise BadInput(f"{where}: target_id {raw!r} is not an integer")
        ids.append(int(f))
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise BadInput(f"{where}: target_id {dup[0]} appears more than once")
    try:
        xyz = df[["x", "y", "z"]].to_numpy(dtype=float)
        nrm = df[["nx", "ny", "nz"]].to_numpy(dtype=float)
    except (TypeError, ValueError) as exc:
        raise BadInput(f"{where}: a coordinate is not a number ({exc})") from None
    for k, tid in enumerate(ids):
        if not (np.all(np.isfinite(xyz[k])) and np.all(np.isfinite(nrm[k]))):
            raise BadInput(f"{where}: target {tid}: centre or normal is not finite")
        if np.linalg.norm(nrm[k]) < 1e-9:
            raise BadInput(f"{where}: target {tid}: plate normal (nx, ny, nz) is zero")
    normals = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    return PlanTargets(ids=np.array(ids, dtype=np.int64), centres=xyz, normals=normals)


def read_targets(path: str | Path) -> PlanTargets:
    """Read a targets CSV (see module docstring).

    Raises
    ------
    BadInput
        File missing or unreadable, or a bad table (:func:`targets_from_frame`).
    """
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: targets file not found")
    try:
        df = pd.read_csv(p, comment="#", skipinitialspace=True)
    except Exception as exc:  # noqa: BLE001 - any parser failure is bad input
        raise BadInput(f"{p}: not a readable CSV ({exc})") from None
    df.columns = [str(c).strip() for c in df.columns]
    return targets_from_frame(df, str(p))
