"""Identification, step 0: the residual corrections in the calibrated flange frame.

See :mod:`pipeline.estimation.correction_frame` for why and the maths (F1)-(F2).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.estimation.correction_frame import (
    MAX_FRAME_DEVIATION,
    frame_deviation,
    translation_map,
)
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.stages.identify.first_fit import first_fit
from pipeline.stages.identify.types import AUTO_ORDER, IdentifyConfig, IdentifyResult, Robot


@dataclass
class Frame:
    """The map applied to the corrections (:func:`correction_frame`) and its summary."""

    M: F64
    summary: dict[str, Any]


def correction_frame(
    robot: Robot,
    data: FitData,
    config: IdentifyConfig,
    fit_one: Callable[[str, IdentifyConfig], IdentifyResult],
) -> tuple[FitData, Frame]:
    """The corrections in the calibrated flange frame (``IdentifyConfig.correction_frame``).

    1. A first fit of the first model of ``AUTO_ORDER`` that can be fitted (prediction
       only, no print shape); 2. ``M_eff``: the map (F1) of
       :mod:`pipeline.estimation.correction_frame` from the nominal to the first fit's
       calibrated chain, at its pin, averaged with every row's pair scatter ``S_i`` (F2)
       where the table has them, else over the used poses (weights ``w_i``);
       3. ``d_i -> M_eff d_i`` for every row, and the print-size levers ``g_i`` likewise
       (flange-frame vectors from the same Jacobian). Nothing changes for ``nominal``,
       when no first fit is possible or when its map is more than
       :data:`pipeline.estimation.correction_frame.MAX_FRAME_DEVIATION` off the identity; ``config.correction_map`` replaces 1-2.
    ``fit_one(model, config)`` fits one error model to ``data``
    (:func:`pipeline.stages.identify.stage._identify_one`) of ``robot``; the first fit is
    made once per process for the same rows and settings
    (:func:`pipeline.stages.identify.first_fit.first_fit`: the outliers stage made it).
    """
    chain = robot.chain
    eye = np.eye(3)
    if config.correction_frame == "nominal":
        return data, Frame(eye, {"method": "nominal", "note": "corrections as the table has them"})
    if config.correction_frame != "calibrated":
        raise BadInput(
            f"correction_frame {config.correction_frame!r}: expected 'calibrated' or 'nominal'"
        )
    if config.correction_map is not None:
        given = np.asarray(config.correction_map, dtype=float)
        return _apply(data, given, {"method": "given", "note": "the full fit's map"})
    first_cfg = dataclasses.replace(
        config, prediction_only=True, target_shape="none", correction_frame="nominal"
    )
    first = None
    for name in AUTO_ORDER:
        try:
            first = first_fit(fit_one, name, robot, data, first_cfg)
            break
        except (BadInput, CalibrationFailed):
            continue
    if first is None:
        return data, Frame(eye, {"method": "nominal", "note": "no first fit: corrections kept"})
    if data.pair_scatter_all is not None:  # (F2): the pairs of every row, used or not
        M = translation_map(
            chain, first.chain, data.q_all, S=data.pair_scatter_all, p_point=first.p_flange_pin
        )
        how = "pair-scatter weighted (F2)"
    else:
        M = translation_map(chain, first.chain, data.q, data.sw**2, p_point=first.p_flange_pin)
        how = "mean over the used poses (F1)"
    dev = frame_deviation(M)
    if dev > MAX_FRAME_DEVIATION:
        return data, Frame(
            eye,
            {
                "method": "nominal",
                "note": f"the first fit's map is {dev:.2f} off the identity (> "
                f"{MAX_FRAME_DEVIATION}): the poses do not determine it; corrections kept",
            },
        )
    return _apply(
        data,
        M,
        {
            "method": "calibrated",
            "first_fit": first.model,
            "average": how,
            "note": "corrections taken from nominal to calibrated flange translations",
        },
    )


def _apply(data: FitData, M: F64, summary: dict[str, Any]) -> tuple[FitData, Frame]:
    """``d_i -> M d_i`` for every row (and the print-size levers); the summary completed."""
    eye = np.eye(3)
    d = data.d @ M.T
    new = dataclasses.replace(
        data,
        d=d,
        d_all=data.d_all @ M.T,
        shape_g=None if data.shape_g is None else data.shape_g @ M.T,
    )
    moved = np.linalg.norm(d - data.d, axis=1) * 1e6
    big = float(moved.max()) if len(moved) else 0.0
    return new, Frame(
        M,
        {
            **summary,
            "matrix_minus_identity": (M - eye).tolist(),
            "rms_change_um": float(np.sqrt(np.mean(moved**2))) if len(moved) else 0.0,
            "max_change_um": big,
            "note": f"{summary['note']} (M - I up to {np.abs(M - eye).max():.1e}; "
            f"the corrections moved by up to {big:.1f} um)",
        },
    )
