"""Cross-validation's refits: fits on subsets of one touch-up table's rows.

A refit on the rows ``use`` of a table is identification on the table with
``inlier = use`` (:func:`pipeline.stages.identify.stage.identify`): every other row is
left out as an outlier. Cross-validation makes many (k folds and one per target,
per error model) of the same table, so the table is prepared once
(:func:`pipeline.stages.identify.data.prepare_table`: column checks, numeric
conversion, row reasons, target numbering) and each refit's rows derived from it
by the mask (:func:`pipeline.stages.identify.data.restrict`, equal field by field
to preparing the masked table); the error models are made once per robot
(:class:`pipeline.stages.identify.types.Robot`). The fit itself is identify's
(:func:`pipeline.stages.identify.stage.fit_prepared`), with the settings of
:func:`refit_config`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.stages.identify.data import PreparedTable, prepare_table, restrict
from pipeline.stages.identify.stage import fit_prepared
from pipeline.stages.identify.types import IdentifyConfig, IdentifyResult, Robot


@dataclass
class RefitTable:
    """A touch-up table prepared once for refits on subsets of its rows (:func:`refit`).

    Attributes
    ----------
    df : the table (M rows, index 0..M-1)
    robot : the nominal robot; its error models are made once and shared by the refits
    prep : the table prepared (:func:`pipeline.stages.identify.data.prepare_table`), or
        the error preparing it raised: every refit raises it, as identify on the table would
    """

    df: pd.DataFrame
    robot: Robot
    prep: PreparedTable | BadInput | CalibrationFailed


def refit_table(df: pd.DataFrame, robot: Robot, config: IdentifyConfig) -> RefitTable:
    """Prepare ``df`` (index 0..M-1, attrs empty) for refits of ``robot``.

    ``config`` is read for its known distances only; each refit matches its own to the
    targets it keeps."""
    prep: PreparedTable | BadInput | CalibrationFailed
    try:
        prep = prepare_table(df, robot.chain, config)
    except (BadInput, CalibrationFailed) as exc:
        prep = exc
    return RefitTable(df, robot, prep)


def refit(table: RefitTable, use: np.ndarray, config: IdentifyConfig) -> IdentifyResult:
    """Identify one error model (``config.model``) on the rows ``use`` (M,) of the table.

    The same result as ``identify(table.df.assign(inlier=use), ...)``, without preparing
    the table again. Raises as it does (BadInput, CalibrationFailed).
    """
    if not isinstance(table.prep, PreparedTable):
        raise table.prep
    data = restrict(table.prep, use, config)
    res = fit_prepared(data, table.robot, config, table.df)
    assert isinstance(res, IdentifyResult)
    return res


#: touch-ups of each target a refit needs to fit a print shape the full fit kept (its
#: three parameters per target, and the F-test's spare degrees of freedom)
REFIT_SHAPE_MIN_TOUCHUPS = 4


def refit_config(config: IdentifyConfig, full: Mapping[str, Any]) -> IdentifyConfig:
    """Settings of the refits on part of the touch-ups, from the fit on all of them.

    ``full`` is that fit's summary (:attr:`IdentifyResult.summary`, or its entry in
    ``identify.json["models"]``).

    Two checks of the full fit are not repeated on each subset: the plausibility
    guardrails (the full table passed them, or the user accepted it), and the
    print-shape F-test when it found no print shape on every touch-up (a subset
    has less evidence): the refits then fit none (``target_shape="none"``)
    instead of fitting it to test it. When the full fit kept a print shape,
    each refit tests it again as the identify stage does: fitting it without
    the test would leave the test's choice, made with the held-out touch-ups,
    out of what is validated (measured: 3.5 % lower held-out RMS on the
    standard LR Mate-like cell, an optimistic figure). A refit then needs
    :data:`REFIT_SHAPE_MIN_TOUCHUPS` touch-ups of each target, not the full fit's
    minimum: a fold holding out seven of a target's twelve left it five and
    dropped the print shape of every target, and its held-out touch-ups were
    predicted as perfect circles (held-out RMS 0.34 mm where the calibration was
    good to 0.01 mm, a UR5e-like cell with 60 um out-of-round prints).

    The corrections' map into the calibrated flange frame (``correction_map``) is the
    full fit's: near the identity, a property of the kinematics, not of the held-out rows.
    """
    shape = full.get("print_shape")
    no_shape = isinstance(shape, dict) and shape.get("fitted") is False
    frame = full.get("correction_frame") or {}
    given = frame.get("matrix_minus_identity", np.zeros((3, 3)) if frame else None)
    kept = isinstance(shape, dict) and bool(shape.get("fitted"))
    return dataclasses.replace(
        config,
        check_plausibility=False,
        target_shape="none" if no_shape else config.target_shape,
        shape_min_touchups=(
            min(config.shape_min_touchups, REFIT_SHAPE_MIN_TOUCHUPS)
            if kept
            else config.shape_min_touchups
        ),
        prediction_only=True,
        correction_map=(np.eye(3) + np.asarray(given)).tolist() if given is not None else None,
    )
