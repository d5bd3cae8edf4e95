"""``calibration.json``: the model a run predicts with, complete enough to use without vtcal's run.

``calibrated.urdf`` carries a rigid model; the model the run predicts best with
may hold terms a URDF cannot (``elastic``'s joint compliance, see
:mod:`pipeline.stages.crossval.predictor`). This record carries that model
whole, so ``vtcal predict``, ``vtcal compensate`` and
:func:`pipeline.use.load` rebuild its forward map exactly:

* ``robot``: the nominal URDF text and the base and flange links the model
  corrects (the error model is a correction *of* that chain);
* ``model`` and ``parameters``: the error model's name and its vector ``x``
  in the model's own parameter order (SI: m, rad, rad/(N m)), with the pin
  ``p_flange_pin`` (m, flange frame);
* ``covariance``: the covariance of the estimated parameters (kinematic, then
  the pin), rebuilt from ``parameters.parquet``'s standard errors and
  correlation rows, ``C = D R D``; held parameters are exact (zero variance);
* ``region``: the joint ranges the touch-ups covered (rad), outside which a
  prediction is flagged (:mod:`pipeline.estimation.region`);
* ``mass_model``: what an elastic model assumes (masses, gravity, payload in
  training), from the model itself; absent for a rigid model;
* ``validated``: the model's validated error as the run's verdict states it
  (:func:`pipeline.accuracy.verdict.verdict`: held-out k-fold, or the covariance-predicted
  error where that is larger) and its k-fold figures, mm.

Pure: tables and dicts in, a JSON-ready dict out. Read back by
:func:`pipeline.use.calibration.Calibration.from_record`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

#: the record's format tag (a reader refuses another)
FORMAT = "vtcal calibration 1"


def parameter_vector(
    params: pd.DataFrame, model: str, names: list[str]
) -> tuple[list[float], list[float]]:
    """``(x, pin)`` of ``model`` from ``parameters.parquet``: ``x`` in ``names`` order.

    Raises
    ------
    KeyError
        A parameter of ``names`` (or the pin) is not in the table for ``model``.
    """
    rows = params[params["model"] == model]
    value = dict(zip(rows["name"], rows["value"].astype(float), strict=True))
    x = [float(value[n]) for n in names]
    pin = [float(value[f"pin.{a}"]) for a in "xyz"]
    return x, pin


def parameter_covariance(params: pd.DataFrame, model: str) -> tuple[list[str], list[list[float]]]:
    """The covariance of ``model``'s estimated parameters, ``C = D R D`` (names, matrix).

    ``D = diag(std)`` and ``R`` the correlation rows of the table, both in the
    order of ``estimated_index`` (kinematic parameters, then the pin). A row
    without a finite standard error (no redundancy) gives an empty record.
    """
    rows = params[(params["model"] == model) & (params["estimated_index"] >= 0)]
    rows = rows.sort_values("estimated_index")
    names = [str(n) for n in rows["name"]]
    std = rows["std"].to_numpy(dtype=float)
    if not len(rows) or not np.all(np.isfinite(std)):
        return [], []
    corr = np.array([list(c) for c in rows["correlation"]], dtype=float)
    if corr.shape != (len(rows), len(rows)):
        return [], []
    cov = std[:, None] * corr * std[None, :]
    return names, [[float(v) for v in row] for row in cov]


def _region_rad(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The covered joint ranges of a model's summary (``region.joint_ranges_deg``) in rad."""
    region = summary.get("region") or {}
    ranges = region.get("joint_ranges_deg") or {}
    return {
        "joint_ranges_rad": {
            j: [math.radians(float(a)), math.radians(float(b))] for j, (a, b) in ranges.items()
        },
        "growth": region.get("growth"),
        "note": region.get("note", ""),
    }


def calibration_record(
    params: pd.DataFrame,
    fits: Mapping[str, Any],
    crossval: Mapping[str, Any] | None,
    robot: tuple[str, str, str],
    urdf_model: str,
) -> dict[str, Any]:
    """``calibration.json`` of a run (see the module docstring).

    Parameters
    ----------
    params : ``parameters.parquet`` (every fitted model's rows)
    fits : ``models.json`` (``{"models": {model: summary}, ...}``)
    crossval : cross-validation's summary (``predict_model``, ``predict_choice``,
        per-model figures), or None when it did not run
    robot : ``(nominal URDF text, base link, flange link)``
    urdf_model : the model ``calibrated.urdf`` carries

    Returns
    -------
    dict (JSON-ready): ``format``, ``model``, ``urdf_model``, ``choice``, ``robot``,
    ``joint_names``, ``parameters`` (``names``, ``values``), ``p_flange_pin``,
    ``covariance`` (``names``, ``matrix``), ``region``, ``mass_model``, ``validated``
    """
    from pipeline.accuracy.verdict import verdict
    from pipeline.kinematics.chain import load_chain
    from pipeline.models import get_model

    urdf, base_link, flange_link = robot
    model = urdf_model
    choice = f"predictions use {urdf_model}, the model calibrated.urdf holds"
    if crossval is not None and crossval.get("predict_model") in fits["models"]:
        model = str(crossval["predict_model"])
        choice = str(crossval.get("predict_choice") or choice)
    chain = load_chain(urdf, base_link, flange_link)
    em = get_model(model)(chain)
    x, pin = parameter_vector(params, model, list(em.param_names))
    cov_names, cov = parameter_covariance(params, model)
    mass = em.mass_model() if hasattr(em, "mass_model") else None
    cv = ((crossval or {}).get("models") or {}).get(model) or {}
    judged = verdict({**fits["models"][model], "best_model": model, "crossval": crossval or {}})
    return {
        "format": FORMAT,
        "model": model,
        "urdf_model": urdf_model,
        "urdf_exact": bool(getattr(em, "urdf_exact", True)),
        "choice": choice,
        "robot": {"urdf": urdf, "base_link": base_link, "flange_link": flange_link},
        "joint_names": list(chain.joint_names),
        "parameters": {"names": list(em.param_names), "values": x},
        "p_flange_pin": pin,
        "covariance": {"names": cov_names, "matrix": cov},
        "region": _region_rad(fits["models"][model]),
        "mass_model": mass,
        "validated": {
            "validated_mm": (judged or {}).get("validated_mm"),
            "validated_how": (judged or {}).get("validated_how"),
            "kfold_rms_mm": cv.get("kfold_rms_mm"),
            "kfold_model_rms_mm": cv.get("kfold_model_rms_mm"),
            "train_rms_mm": fits["models"][model].get("rms_mm"),
        },
        "units": "m, rad; compliance rad/(N m); covariance in the parameters' units",
    }
