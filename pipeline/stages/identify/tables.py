"""What a fit of one error model leaves: its three tables and its summary.

Steps 4 and 5 of :func:`pipeline.stages.identify.stage.identify` per model: the
``parameters``, ``residuals`` and ``targets`` tables (``schemas/NAME.json``)
and the JSON summary (figures, held parameters with reasons, predicted
accuracy, solver report, headline) from the solution (:class:`FitFigures`) and
its uncertainty (:class:`Uncertainty`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.estimation.region import region_summary
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.stages.identify.notes import conditioning_note


@dataclass
class Uncertainty:
    """The covariance of a fit, ``cov = sigma^2 (J^T J)^-1`` over the estimated unknowns.

    Attributes
    ----------
    std_z : (Z,) standard errors of the estimated unknowns (kinematic, pin, targets)
    corr : (E, E) correlations of the kinematic and pin estimates
    sigma2 : ``|r|^2 / (m - p)`` (m^2), NaN without redundancy
    dof : ``m - p``
    obs : observability indices and condition number of the reduced Jacobian
    pred : ``{"shape"|"absolute"|"raw": (W,) predicted pin errors (m)}`` over workspace poses
    cov : (Z, Z) the covariance itself, in the order of ``std_z`` (kinematic, pin, targets)
    spread : ``{"shape"|"absolute"|"raw": error_spread dict}``: how far one calibration's
        true RMS error may fall from the predicted one (:mod:`pipeline.estimation.spread`)
    """

    std_z: F64
    corr: F64
    sigma2: float
    dof: int
    obs: dict[str, float]
    pred: dict[str, F64]
    cov: F64 | None = None
    spread: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class FitFigures:
    """A solved fit of one error model, as the tables and the summary read it."""

    name: str
    model: Any  # the ErrorModel
    data: FitData
    kept: np.ndarray  # identified kinematic columns
    reasons: dict[int, str]  # held column -> why
    not_excited: list[str]
    n_structural: int
    x: F64  # (P,) model parameters
    pin: F64  # (3,) p_flange_pin
    pin0: F64  # (3,) its start (the linear solution at nominal kinematics)
    tg: F64  # (K, 3) p_base_target
    norms_used: F64  # (N,) pin-to-target distances of the used rows (m)
    shape: dict[str, Any] | None
    noise_note: str
    components: dict[str, Any] | None  # per-target variance components (identify.components)
    sigma_flange: F64 | None
    sol: Any  # scipy OptimizeResult
    method: str
    loss: str  # the robust loss asked for
    initial_rms: float
    Lc: float


def covariance_names(param_names: list[str], kept: Any, target_labels: list[str]) -> list[str]:
    """Names of :attr:`Uncertainty.cov`'s unknowns: the kept parameters, ``pin.x/y/z``, then
    ``target.LABEL.x/y/z`` in the fit's target order."""
    names = [param_names[int(j)] for j in kept] + [f"pin.{c}" for c in "xyz"]
    return names + [f"target.{lab}.{c}" for lab in target_labels for c in "xyz"]


def parameter_table(f: FitFigures, u: Uncertainty) -> pd.DataFrame:
    """``parameters`` rows: every kinematic parameter (held ones with the reason), then the pin."""
    model, kept, x, dof = f.model, f.kept, f.x, u.dof
    P = model.n_params
    est_index = -np.ones(P, dtype=np.int64)
    est_index[kept] = np.arange(len(kept))
    nominal_vals = model.param_nominal
    prow = []
    for j in range(P):
        i = int(est_index[j])
        prow.append(
            {
                "model": f.name,
                "name": model.param_names[j],
                "kind": "kinematic",
                "joint": model.param_joints[j],
                "unit": model.param_units[j],
                "nominal": float(nominal_vals[j]),
                "value": float(x[j]),
                "std": float(u.std_z[i]) if i >= 0 and dof > 0 else float("nan"),
                "identifiable": i >= 0,
                "held_reason": "" if i >= 0 else f.reasons.get(j, "not identifiable"),
                "estimated_index": i,
                "correlation": list(map(float, u.corr[i])) if i >= 0 else [],
            }
        )
    for c, axis in enumerate("xyz"):
        i = len(kept) + c
        prow.append(
            {
                "model": f.name,
                "name": f"pin.{axis}",
                "kind": "pin",
                "joint": "",
                "unit": "m",
                "nominal": float(f.pin0[c]),
                "value": float(f.pin[c]),
                "std": float(u.std_z[i]) if dof > 0 else float("nan"),
                "identifiable": True,
                "held_reason": "",
                "estimated_index": i,
                "correlation": list(map(float, u.corr[i])),
            }
        )
    return pd.DataFrame(prow)


def residual_table(f: FitFigures) -> pd.DataFrame:
    """``residuals`` rows: every input row, its pin position and residual (NaN where unusable)."""
    data = f.data
    rows = data.rows.copy()
    M = len(rows)
    res = np.full((M, 3), np.nan)
    pos = np.full((M, 3), np.nan)
    ok = np.all(np.isfinite(data.q_all), axis=1)
    if ok.any():
        pa, _, _ = f.model.pin_and_jacobian(f.x, data.q_all[ok], f.pin + data.d_all[ok], jac=False)
        pos[ok] = pa
        has_t = ok & (data.tk_all >= 0)
        res[has_t] = pos[has_t] - f.tg[data.tk_all[has_t]]
    return pd.DataFrame(
        {
            "model": f.name,
            "touchup_id": rows["touchup_id"],
            "target_id": rows["target_id"],
            "target_label": rows["target_label"],
            "used": rows["used"],
            "reason": rows["reason"],
            "weight": rows["weight"],
            "rx": res[:, 0],
            "ry": res[:, 1],
            "rz": res[:, 2],
            "norm": np.linalg.norm(res, axis=1),
            "px": pos[:, 0],
            "py": pos[:, 1],
            "pz": pos[:, 2],
        }
    )


def target_table(f: FitFigures, u: Uncertainty) -> pd.DataFrame:
    """``targets`` rows: each target centre in the base frame, its standard errors, its print."""
    data, tg, K, kept = f.data, f.tg, f.data.K, f.kept
    tstd = u.std_z[len(kept) + 3 :].reshape(K, 3) if u.dof > 0 else np.full((K, 3), np.nan)
    targets = pd.DataFrame(
        {
            "model": f.name,
            "target_id": np.array(data.target_ids, dtype=np.int64),
            "target_label": data.target_labels,
            "x": tg[:, 0],
            "y": tg[:, 1],
            "z": tg[:, 2],
            "std_x": tstd[:, 0],
            "std_y": tstd[:, 1],
            "std_z": tstd[:, 2],
            "n_touchups": np.bincount(data.tk, minlength=K).astype(np.int64),
        }
    )
    shape = f.shape
    fitted = shape is not None and bool(shape.get("fitted"))
    for key in ("kappa", "ellipticity", "orientation_rad", "diameter_error_um", "out_of_round_um"):
        vals = [t.get(key, np.nan) for t in shape["targets"]] if fitted and shape else [np.nan] * K
        targets[f"print_{key}"] = np.asarray(vals, dtype=float)
    return targets


def weighted_rms(norms: F64, sw: F64) -> float:
    """Weighted RMS of the pin-to-target distances, ``sqrt(sum w_i |e_i|^2 / sum w_i)``.

    ``norms`` (N,) m, ``sw`` (N,) the rows' square-root weights (``w_i = sw_i^2``).
    """
    return float(np.sqrt(np.sum(norms**2 * sw**2) / float(np.sum(sw**2))))


def fit_summary(f: FitFigures, u: Uncertainty) -> dict[str, Any]:
    """The JSON summary of one model's fit (identify.json ``models[MODEL]``), headline included.

    ``rms_mm`` is the weighted RMS of the pin-to-target distances,
    ``sqrt(sum w_i |e_i|^2 / sum w_i)``; the predicted figures are RMS and max
    of :attr:`Uncertainty.pred`. The wall time (``seconds``) is added by the caller.
    """
    model, data, kept, name, sol, dof, obs = f.model, f.data, f.kept, f.name, f.sol, u.dof, u.obs
    P, K, N, M = model.n_params, data.K, len(data.q), len(data.rows)
    rms = weighted_rms(f.norms_used, data.sw)
    held = np.array(sorted(f.reasons), dtype=np.int64)
    held_list = [
        {"name": model.param_names[int(j)], "reason": f.reasons.get(int(j), "")} for j in held
    ]
    summary: dict[str, Any] = {
        "print_shape": f.shape,
        "model": name,
        "model_description": model.description,
        "n_rows": int(M),
        "n_used": int(N),
        "n_targets": int(K),
        "n_params": int(P),
        "n_identified": int(len(kept)),
        "n_structural": int(f.n_structural),
        "unidentifiable": [h["name"] for h in held_list],
        "held": held_list,
        **_scale_fields(len(data.dist)),
        "noise_model": f.noise_note,
        "variance_components": f.components,
        "flange_sigma_mm": (
            [float(v) * 1e3 for v in f.sigma_flange] if f.sigma_flange is not None else None
        ),
        "distances": _distance_rows(f),
        "distances_dropped": data.dropped_distances,
        "cost": float(sol.cost),
        "rms_mm": rms * 1e3,
        "max_mm": float(f.norms_used.max() * 1e3),
        "sigma_mm": math.sqrt(u.sigma2) * 1e3 if dof > 0 else float("nan"),
        "dof": int(dof),
        **{k: float(v) for k, v in obs.items()},
        **_predicted_fields(u),
        "p_flange_pin": [float(v) for v in f.pin],
        "solver": _solver_fields(f),
    }
    summary["conditioning_note"], weak = conditioning_note(
        f.not_excited, int(f.n_structural), float(obs["cond"])
    )
    summary["not_excited"] = f.not_excited
    if dof > 0:
        summary["region"] = region_summary(
            model.nominal.joint_names,
            data.q,
            summary["predicted_shape_rms_mm"],
            summary["predicted_beyond_rms_mm"],
        )
    summary["headline"] = [
        f"identify [{name}]: {N} touch-ups, {K} targets, {len(kept)}/{P} parameters identified; "
        f"residual RMS {rms * 1e3:.4f} mm, covariance-predicted pin error RMS "
        f"{summary['predicted_shape_rms_mm']:.4f} mm (shape), "
        f"{summary['predicted_absolute_rms_mm']:.4f} mm (absolute); cond {obs['cond']:.3g}",
        "scale: " + summary["scale_note"],
    ] + (["conditioning: " + summary["conditioning_note"]] if weak else [])
    if not model.urdf_exact:
        summary["urdf_note"] = (
            f"calibrated URDF of model {name}: its rigid part only (a URDF cannot carry its "
            "configuration-dependent terms); the residuals and figures above are the whole "
            "model's, its values are in parameters.parquet"
        )
        summary["headline"].insert(1, summary["urdf_note"])
    return summary


def _scale_fields(n_distances: int) -> dict[str, Any]:
    """identify.json's length-scale and gauge fields: held without a known distance."""
    scale_held = not n_distances
    return {
        "scale_held": scale_held,
        "scale_note": (
            "no known distance: the length scale was not identifiable and was held at the "
            "nominal model's; only shape accuracy applies"
            if scale_held
            else f"length scale identified from {n_distances} known distance(s)"
        ),
        "base_note": "the base frame against the targets is held at nominal (never identifiable)",
        "unidentifiable_directions": [
            "base frame against the targets (6 directions): held at nominal",
            "virtual pin against the last joint's own motion: absorbed by the pin",
        ]
        + (
            ["length scale (no known distance): held at the nominal model's by a gauge constraint"]
            if scale_held
            else []
        ),
    }


def _distance_rows(f: FitFigures) -> list[dict[str, Any]]:
    """Each known distance, given and fitted (between the fitted target positions)."""
    data = f.data
    return [
        {
            "a": data.target_labels[a],
            "b": data.target_labels[b],
            "metres": dm,
            "fitted_metres": float(np.linalg.norm(f.tg[a] - f.tg[b])),
        }
        for a, b, dm in data.dist
    ]


def _predicted_fields(u: Uncertainty) -> dict[str, Any]:
    """RMS and max (mm) of each kind of :attr:`Uncertainty.pred`, NaN without redundancy
    (``beyond``: the shape error just outside the covered joint ranges, :mod:`pipeline.
    estimation.region`), and for shape and absolute the spread of one calibration's true
    RMS error about it (``predicted_KIND_spread``: :mod:`pipeline.estimation.spread`)."""
    return {
        **{
            f"predicted_{kind}_{stat}_mm": (float(fn(e) * 1e3) if u.dof > 0 else float("nan"))
            for kind, e in u.pred.items()
            for stat, fn in (("rms", lambda a: np.sqrt(np.mean(a**2))), ("max", np.max))
        },
        **{
            f"predicted_{kind}_spread": sp
            for kind, sp in u.spread.items()
            if kind in ("shape", "absolute") and u.dof > 0
        },
        "predicted_note": (
            "covariance-predicted pin position error over poses spread through the touched "
            "volume, after the same registration as the accuracy figures (shape: similarity, "
            "absolute: rigid; raw: none); random error only (systematic input errors are "
            "invisible to it)"
        ),
    }


def _solver_fields(f: FitFigures) -> dict[str, Any]:
    """How the least-squares solve went (identify.json ``solver``)."""
    sol = f.sol
    return {
        "method": f.method,
        "loss": f.loss,
        "status": int(sol.status),
        "message": str(sol.message),
        "success": bool(sol.success),
        "nfev": int(sol.nfev),
        "njev": int(sol.njev or 0),
        "initial_rms_mm": f.initial_rms * 1e3,
        "characteristic_length_m": f.Lc,
    }


def strict_json(doc: Any) -> Any:
    """``doc`` as strict JSON data: NaN and inf as None, numpy values as Python ones."""
    import json

    return json.loads(json.dumps(_finite(doc), default=_json_default, allow_nan=False))


def _finite(o: Any) -> Any:
    """NaN/inf floats -> None, recursively (strict JSON)."""
    if isinstance(o, float | np.floating):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_finite(v) for v in o]
    return o


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
