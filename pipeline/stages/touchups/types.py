"""The touch-up stage's intermediate records: captures, designated values, tilt.

Shared by :mod:`pipeline.stages.touchups.stage` (steps 1-4) and
:mod:`pipeline.stages.touchups.rows` (step 5, one row per touch-up).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import pandas as pd


@dataclass
class Captures:
    """The frames joined with their detections, one entry per image in frame order."""

    df: pd.DataFrame
    names: list[str]  # joint names
    Q: np.ndarray  # (n, dof) joint vectors
    T: np.ndarray  # (n, 4, 4) nominal flange poses
    found: np.ndarray
    good: np.ndarray  # found, with a good quality
    still: np.ndarray  # neither moving nor in a joint-state gap
    u: np.ndarray
    v: np.ndarray
    s: np.ndarray
    _columns: dict[tuple[str, str, str], np.ndarray] = field(
        default_factory=dict, repr=False, compare=False
    )

    def column(self, name: str, dtype: Any, fill: Any = None) -> np.ndarray:
        """Column ``name`` of :attr:`df` as an array of ``dtype`` (missing values ``fill``),
        converted once: every touch-up's row reads the same few columns."""
        key = (name, repr(dtype), repr(fill))
        if key not in self._columns:
            col = self.df[name] if fill is None else self.df[name].fillna(fill)
            self._columns[key] = col.to_numpy(dtype)
        return self._columns[key]


class Designated(NamedTuple):
    """The designated centre and size, and the convergence thresholds (px)."""

    u0: float
    v0: float
    s0: float
    thr: float
    thr_s: float


class Tilt(NamedTuple):
    """Per touch-up tilt bias (:func:`pipeline.stages.touchups.tilt.tilt_bias`) and view geometry (:func:`pipeline.measurement.image.view_geometry`)."""

    bias: np.ndarray  # (n, 3)
    tilt_deg: np.ndarray  # (n,)
    resolved: np.ndarray  # (n,)
    view_g: np.ndarray  # (3,)
    axis_l: np.ndarray  # (n, 3)


def pose_key(T: np.ndarray) -> tuple[int, int, int]:
    """Position rounded to 20 um: captures at one pose share the key."""
    p = np.round(T[:3, 3] / 2e-5).astype(int)
    return int(p[0]), int(p[1]), int(p[2])
