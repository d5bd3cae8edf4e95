"""Held-out predictions of cross-validation: fit without a fold, predict the pin at it.

The k-fold core of :mod:`pipeline.stages.crossval.stage`: each fold's touch-ups are
predicted by the model fitted on the others, with the print shape that fit kept.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.kinematics.se3 import F64
from pipeline.stages.crossval.refit import RefitTable, refit, refit_table
from pipeline.stages.identify.data import PreparedTable
from pipeline.stages.identify.types import IdentifyConfig, IdentifyResult, PrintRows, Robot


def joints_and_corrections(df: pd.DataFrame, names: list[str]) -> tuple[F64, F64]:
    """Every row's joint vector (M, n) and residual correction (M, 3) m, 0 where missing."""
    q_all = df[names].to_numpy(dtype=float)
    d_all = np.zeros((len(df), 3))
    for j, c in enumerate(("dx_flange", "dy_flange", "dz_flange")):
        if c in df.columns:
            d_all[:, j] = np.nan_to_num(df[c].to_numpy(dtype=float))
    return q_all, d_all


def predict_pins(res: IdentifyResult, q: F64, d: F64, shape: PrintRows | None = None) -> F64:
    """Pin positions of the fitted model, ``T(q_i) (pin + d_i + eps_i g_i)`` -> (N, 3).

    The model's own map (a model a URDF cannot carry, e.g. ``elastic``, is
    judged as it predicts, not by its rigid part), and the print shape the fit kept
    (:meth:`IdentifyResult.predict`): a held-out touch-up of a target whose print is
    out of round stops off its centre by the print error the training fit found for
    its view. Judged without that term, the held-out error carried the print's
    ``z eps`` (0.12 mm RMS where the truth was 0.014 mm, UR5e-like cell, 20 um out of
    round, seed 8): a refit that models less than the shipped fit does.
    """
    return res.predict(q, d, shape)


def _print_rows(rt: RefitTable, rows: np.ndarray) -> PrintRows | None:
    """The rows' print-shape geometry from the prepared table, None without its columns."""
    prep = rt.prep
    if not isinstance(prep, PreparedTable) or prep.shape_all is None:
        return None
    sh = prep.shape_all[rows]
    v = sh[:, 6] if sh.shape[1] > 6 else None
    return PrintRows(sh[:, :3], sh[:, 3:6], rt.df["target_id"].to_numpy()[rows], v)


def heldout_predictions(
    table: pd.DataFrame,
    use: np.ndarray,
    fold: np.ndarray,
    urdf: str,
    base_link: str,
    flange_link: str,
    config: IdentifyConfig,
    *,
    every_row: bool = False,
) -> pd.DataFrame:
    """Fit without each fold; predict the pin at the fold's touch-ups (k-fold core).

    Parameters
    ----------
    table : touch-up table
    use : (M,) bool, usable rows
    fold : (M,) fold index per row (-1 for unused rows)
    urdf, base_link, flange_link : the nominal robot
    config : identification settings (one model)
    every_row : also predict at the fold fit's training rows (``held`` false), e.g. to
        register a fold's model to a reference before judging its held-out rows

    Returns
    -------
    DataFrame, one row per usable row (per fold with ``every_row``): ``row``
    (position in ``table``), ``held``, ``fold``,
    ``n_train``, predicted pin ``px, py, pz`` (left side of (1)), the training
    fit's target ``tx, ty, tz`` (NaN if the target has no training data),
    the training fit's per-axis ``sigma_m`` and ``status`` ('' or why not scored).
    """
    df = table.reset_index(drop=True)
    df.attrs = {}  # pandas deep-copies attrs on every operation: the folds need none
    t = refit_table(df, Robot.load(urdf, base_link, flange_link), config)
    return _heldout(t, use, fold, config, every_row)


def _heldout(
    rt: RefitTable, use: np.ndarray, fold: np.ndarray, config: IdentifyConfig, every_row: bool
) -> pd.DataFrame:
    """:func:`heldout_predictions` on a table prepared for refits."""
    return pd.DataFrame(held_rows(rt, use, fold, config, every_row), columns=_PRED_COLUMNS)


#: the columns of :func:`heldout_predictions`' table
_PRED_COLUMNS = "row held fold n_train px py pz tx ty tz sigma_m status".split()


def held_rows(
    rt: RefitTable, use: np.ndarray, fold: np.ndarray, config: IdentifyConfig, every_row: bool
) -> list[dict[str, Any]]:
    """The rows of :func:`heldout_predictions`' table, one dict each (its columns)."""
    table = rt.df
    q_all, d_all = joints_and_corrections(table, list(rt.robot.chain.joint_names))
    tid = table["target_id"].to_numpy()
    out: list[dict[str, Any]] = []
    nan3 = (math.nan, math.nan, math.nan)
    for f in sorted(set(fold[use].tolist())):
        held = use & (fold == f)
        train = use & (fold != f)
        hi = np.flatnonzero(use if every_row else held)
        try:
            res = refit(rt, train, config)
        except (BadInput, CalibrationFailed) as exc:
            for i in hi:
                out.append(
                    _pred_row(i, f, held, train, nan3, nan3, math.nan, f"fold not fitted: {exc}")
                )
            continue
        tg = res.target_xyz
        p = predict_pins(res, q_all[hi], d_all[hi], _print_rows(rt, hi))
        sig = float(res.summary.get("sigma_mm", math.nan)) / 1e3
        for j, i in enumerate(hi):
            t = tg.get(int(tid[i]))
            if t is None:
                out.append(_pred_row(i, f, held, train, p[j], nan3, sig, "target not in training"))
            else:
                out.append(_pred_row(i, f, held, train, p[j], t, sig, ""))
    return out


def _pred_row(
    i: Any, f: int, held: np.ndarray, train: np.ndarray, p: Any, t: Any, sig: float, status: str
) -> dict[str, Any]:
    return {
        "row": int(i),
        "held": bool(held[i]),
        "fold": int(f),
        "n_train": int(train.sum()),
        "px": float(p[0]),
        "py": float(p[1]),
        "pz": float(p[2]),
        "tx": float(t[0]),
        "ty": float(t[1]),
        "tz": float(t[2]),
        "sigma_m": sig,
        "status": status,
    }
