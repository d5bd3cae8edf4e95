"""The rows of ``vtcal predict`` and ``vtcal compensate``: pure, arrays in, DataFrames out.

``schemas/predictions.json`` and ``schemas/compensated.json`` declare them.
Rows with different payloads are computed per payload (an elastic model's
gravity torque changes with it, :mod:`pipeline.use.calibration`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from pipeline.kinematics.se3 import F64

#: target table columns: the position (m, base frame) and, for a flange pose, the orientation
POSITION = ("x", "y", "z")
ORIENTATION = ("qx", "qy", "qz", "qw")


def _groups(payload: F64) -> list[tuple[float | None, np.ndarray]]:
    """Row indices per payload value (None for NaN: the calibration's own)."""
    out: list[tuple[float | None, np.ndarray]] = []
    nan = np.isnan(payload)
    if nan.any():
        out.append((None, np.flatnonzero(nan)))
    for v in np.unique(payload[~nan]):
        out.append((float(v), np.flatnonzero(payload == v)))
    return out


def predict_rows(cal: Any, q: F64, payload: F64) -> pd.DataFrame:
    """One ``predictions`` row per joint vector of ``q`` (N, n), ``payload`` (N,) kg or NaN."""
    N = len(q)
    T = np.empty((N, 4, 4))
    pin = np.empty((N, 3))
    sigma = np.empty(N)
    inside = np.empty(N, dtype=bool)
    outside = [""] * N
    for kg, idx in _groups(payload):
        pr = cal.forward(q[idx], payload_kg=kg)
        T[idx], pin[idx], sigma[idx] = pr.T_base_flange, pr.p_base_pin, pr.sigma_pin_m
        inside[idx] = pr.inside
        for i, names in zip(idx, pr.outside, strict=True):
            outside[i] = names
    quat = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # x, y, z, w
    df = pd.DataFrame({"row": np.arange(N, dtype=np.int64), "payload_kg": payload})
    for j, name in enumerate(cal.joint_names):
        df[name] = q[:, j]
    for a, i in zip("xyz", range(3), strict=True):
        df[f"pin_{a}_m"] = pin[:, i]
    for a, i in zip("xyz", range(3), strict=True):
        df[f"flange_{a}_m"] = T[:, i, 3]
    for a, i in zip(("qx", "qy", "qz", "qw"), range(4), strict=True):
        df[f"flange_{a}"] = quat[:, i]
    df["sigma_pin_m"] = sigma
    df["inside_region"] = inside
    df["outside_joints"] = outside
    return df


def target_poses(df: pd.DataFrame, values: F64, has_orientation: bool) -> F64:
    """(N, 4, 4) targets from the position (and quaternion) columns' ``values`` (N, 3 or 7)."""
    T = np.tile(np.eye(4), (len(df), 1, 1))
    T[:, :3, 3] = values[:, :3]
    if has_orientation:
        T[:, :3, :3] = Rotation.from_quat(values[:, 3:7]).as_matrix()
    return T


def compensate_rows(cal: Any, T: F64, q0: F64, point: str, payload: F64) -> pd.DataFrame:
    """One ``compensated`` row per target ``T`` (N, 4, 4) from starting joints ``q0`` (N, n)."""
    N = len(T)
    q = np.empty_like(q0)
    res_m, res_rad = np.empty(N), np.empty(N)
    conv, within = np.empty(N, dtype=bool), np.empty(N, dtype=bool)
    inside = np.empty(N, dtype=bool)
    outside = [""] * N
    for kg, idx in _groups(payload):
        sol = cal.inverse(T[idx], q0[idx], point=point, payload_kg=kg)
        q[idx], res_m[idx], res_rad[idx] = sol.q, sol.residual_m, sol.residual_rad
        conv[idx], within[idx], inside[idx] = sol.converged, sol.within_limits, sol.inside
        for i, names in zip(idx, sol.outside, strict=True):
            outside[i] = names
    df = pd.DataFrame({"row": np.arange(N, dtype=np.int64), "point": point, "payload_kg": payload})
    for a, i in zip("xyz", range(3), strict=True):
        df[f"target_{a}_m"] = T[:, i, 3]
    for j, name in enumerate(cal.joint_names):
        df[name] = q[:, j]
    df["residual_m"] = res_m
    df["residual_rad"] = res_rad
    df["joint_change_rad"] = np.abs(q - q0).max(axis=1)
    df["converged"] = conv
    df["within_limits"] = within
    df["inside_region"] = inside
    df["outside_joints"] = outside
    return df


def nominal_targets(cal: Any, q: F64, point: str) -> F64:
    """Where the NOMINAL robot puts the flange (pose) or the pin at the program's joints ``q``.

    A joint program taught or computed on the nominal model meant these poses;
    compensation finds the joints that reach them on the calibrated robot.
    """
    from pipeline.kinematics.chain import fk

    T: F64 = fk(cal.chain, q)
    if point == "pin":
        T = T.copy()
        T[:, :3, 3] = np.einsum("nij,j->ni", T[:, :3, :3], cal.p_flange_pin) + T[:, :3, 3]
    return T


def region_line(out: pd.DataFrame) -> str:
    """One sentence: how many rows leave the covered joint ranges, and through which joints."""
    inside = out["inside_region"].to_numpy(dtype=bool)
    if inside.all():
        return "every row inside the joint ranges the calibration covered"
    joints = sorted({j for s in out["outside_joints"] for j in str(s).split(",") if j})
    return (
        f"{int((~inside).sum())} of {len(inside)} rows outside the joint ranges the calibration "
        f"covered ({', '.join(joints)}): predictions there are extrapolated (inside_region false)"
    )
