"""The rows identification fits: :class:`FitData`, what the identify stage prepares.

Built from a touch-up table by :func:`pipeline.stages.identify.data.prepare_data`
(every input row kept with the reason it was or was not used), and read by
eq. (1)'s :class:`pipeline.measurement.pin.Problem`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.kinematics.se3 import F64


@dataclass
class FitData:
    """The rows that enter the fit, and bookkeeping for every input row."""

    q: F64  # (N, n) used rows
    d: F64  # (N, 3)
    sw: F64  # (N,) sqrt weights
    tk: np.ndarray  # (N,) target index 0..K-1 among used targets
    K: int
    target_ids: list[int]  # per used target index
    target_labels: list[str]
    dist: list[tuple[int, int, float]]  # (target index A, B, metres)
    dropped_distances: list[str]
    rows: (
        pd.DataFrame
    )  # every input row: touchup_id, target_id, target_label, used, reason, weight, q...
    used_idx: np.ndarray  # positions of used rows in ``rows``
    q_all: F64  # (M, n) all rows (NaN where missing)
    d_all: F64
    tk_all: np.ndarray  # target index per row (-1 if target not used)
    #: (N, 3) each used row's print-size lever ``g`` and (N, 3) long-axis direction ``l``
    #: (flange frame, :mod:`pipeline.stages.identify.print_shape`), None without those columns
    shape_g: F64 | None = None
    shape_l: F64 | None = None
    #: (N,) each used row's image anisotropy ``|v_i|`` of (S3) (NaN where unknown), None
    #: without the column: (S2) of :mod:`pipeline.stages.identify.print_shape`
    shape_v: F64 | None = None
    #: (M, 3, 3) every row's image-Jacobian pair scatter ``S_i`` (flange frame, m^2,
    #: :mod:`pipeline.estimation.correction_frame` F2), None without those columns
    pair_scatter_all: F64 | None = None
