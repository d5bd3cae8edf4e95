"""Outlier rejection: flag touch-ups that identification must not trust (never delete them).

Rule-based rejection from what extraction recorded about each touch-up. Every
rejected row keeps its data and gets a ``reason``; several reasons are joined
by ``"; "``. Rules (a rule whose column is absent from the touch-up table is
skipped):

| reason | when |
|---|---|
| ``not converged`` | ``converged`` is false |
| ``target lost`` | ``lost`` is true |
| ``captured while moving`` | ``moving`` is true |
| ``poor contour fit`` | ``fit_residual_px`` above ``max_fit_residual_px`` |
| ``ambiguous blob`` | ``ambiguous`` is true |
| ``contour cut by the border`` | ``border_contact`` is true |
| ``too few captures`` | ``n_converged_captures`` below ``min_captures`` |
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

INLIER_COLUMNS = (
    "touchup_id",
    "target_id",
    "dx_flange",
    "dy_flange",
    "dz_flange",
    "weight",
    "converged",
    "stamp_ns",
)


@dataclass
class OutlierConfig:
    """Thresholds of the rejection rules."""

    max_fit_residual_px: float = 0.25
    min_captures: int = 1


def _rule_masks(table: pd.DataFrame, config: OutlierConfig) -> dict[str, np.ndarray]:
    n = len(table)

    def col(name: str, default: Any) -> np.ndarray:
        if name in table.columns:
            return table[name].fillna(default).to_numpy()
        return np.full(n, default)

    return {
        "not converged": ~col("converged", True).astype(bool),
        "target lost": col("lost", False).astype(bool),
        "captured while moving": col("moving", False).astype(bool),
        "poor contour fit": col("fit_residual_px", 0.0).astype(float) > config.max_fit_residual_px,
        "ambiguous blob": col("ambiguous", False).astype(bool),
        "contour cut by the border": col("border_contact", False).astype(bool),
        "too few captures": col("n_converged_captures", config.min_captures).astype(float)
        < config.min_captures,
    }


def flag_outliers(table: pd.DataFrame, info: Any, config: OutlierConfig) -> pd.DataFrame:
    """Flag rejected touch-ups with their reasons.

    Parameters
    ----------
    table : touchups artefact (``schemas/touchups.json``)
    info : RecordingInfo (for the joint names)
    config : OutlierConfig

    Returns
    -------
    DataFrame per ``schemas/inliers.json``: the spec's touch-up columns, the joint
    columns, ``inlier`` and ``reason``; one row per input row, same order.
    """
    joints = list(info.joint_names)
    out = table[list(INLIER_COLUMNS) + joints].copy()
    out.insert(2, "source_target_id", table["target_id"].to_numpy())
    masks = _rule_masks(table, config)
    reasons = ["; ".join(r for r, m in masks.items() if m[i]) for i in range(len(table))]
    out["inlier"] = [r == "" for r in reasons]
    out["reason"] = reasons
    return out.reset_index(drop=True)
