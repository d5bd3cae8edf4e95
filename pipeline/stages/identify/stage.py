"""Identification: from converged touch-ups to a calibrated robot.

Measurement model (one row ``i`` per converged touch-up of target ``k``)::

    T_base_flange(q_i; x) @ (p_flange_pin + d_i) = p_base_target[k]          (1)

with ``x`` the error model's kinematic corrections (:mod:`pipeline.models`),
``p_flange_pin`` the virtual pin, ``d_i`` the residual correction
``(dx, dy, dz)_flange`` of the touch-up (``spec/touchups.md``) and
every target position unknown. A known distance ``D`` between targets ``A``
and ``B`` adds the residual ``w_D (|p_A - p_B| - D)`` with a strong weight
``w_D``. Rows are weighted by ``sqrt(weight)``.

Solver: Levenberg-Marquardt (MINPACK through ``scipy.optimize.least_squares``;
TRF when a robust loss is asked for) with the analytic Jacobian of (1):
``d/dx`` from the model, ``d/dp_pin = R_base_flange``, ``d/dp_target = -I``.
Parameters are scaled by ``ErrorModel.column_scale`` (radians by the working radius ``L``, ``x_scale = 1/L``)
so a radian and the metre it moves the pin by weigh alike. The pin and targets
start from the exact linear least-squares solution of (1) at nominal kinematics.

Noise model: a touch-up's error is fixed in the flange (camera) frame and far
larger along the view than across it. After an isotropic fit the residuals'
3x3 covariance in the flange frame is estimated and the fit repeated with the
residuals whitened, ``W R_i^T (p_i - t_k)`` (feasible generalised least
squares; ``noise_model="isotropic"`` skips it). Whether the targets' touch-ups scatter
alike is tested and reported; asked for, unequal ones are weighed apart
(:mod:`pipeline.stages.identify.components`).

Identifiability: redundancies are exact only where residuals vanish, so they
are found on exact synthetic touch-ups of the nominal robot (cached per robot
and model): the scaled kinematic columns, with the pin and target columns
projected out, go through a QR factorisation with column pivoting (Businger &
Golub 1965; the base-parameter method of Gautier & Khalil 1990 / Hollerbach &
Wampler 1996). Columns whose pivot is below ``rank_tol`` times the largest are
held at nominal and named with a reason: absorbed by the targets or the pin
(base frame, pin against the last joint) or redundant with named identified
parameters. Without a known distance the uniform scale is held by a gauge row
``v . x = 0`` (``v`` the model direction of a uniform scale). A second pivoted
QR on the actual touch-ups (``data_tol``) holds what these poses fail to excite.

Uncertainty: ``cov = sigma^2 (J^T J)^-1`` over the estimated unknowns with
``sigma^2 = |r|^2 / (m - p)``; standard errors, the correlation matrix, and the
pin position error the covariance predicts over poses spread through the
touched volume (``sqrt(mean trace(J_w cov J_w^T))``). A covariance sees only
random error: systematic input errors are invisible to it.

Observability indices O1..O5 (:mod:`pipeline.models.observability`) of the
reduced Jacobian are recorded with its condition number.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from pipeline.accuracy.evaluate import workspace_poses
from pipeline.errors import BadInput, CalibrationFailed
from pipeline.estimation.identifiability import select_columns
from pipeline.estimation.loss import partial_loss
from pipeline.estimation.region import predicted_over, widened_poses
from pipeline.estimation.uncertainty import (
    covariance,
    pin_offset_left,
    predicted_errors,
    residual_variance,
    with_pin_offset,
)
from pipeline.estimation.whitening import flange_residual_cov, flange_whitening
from pipeline.kinematics.se3 import F64
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.measurement.data import FitData
from pipeline.measurement.pin import Problem, initial_pin_targets
from pipeline.models import model_names
from pipeline.models.observability import indices_from_singular_values, project_out
from pipeline.stages.identify.components import weigh_targets
from pipeline.stages.identify.data import implausible_rows, prepare_data, refuse_early
from pipeline.stages.identify.frame import correction_frame
from pipeline.stages.identify.notes import COND_WARN, conditioning_note
from pipeline.stages.identify.print_shape import ShapeFit
from pipeline.stages.identify.shape import fit_print_shape, spent_unknowns
from pipeline.stages.identify.structure import (
    design_jacobian,
    share_exact_touchups,
    structure,
)
from pipeline.stages.identify.tables import (
    FitFigures,
    Uncertainty,
    covariance_names,
    fit_summary,
    parameter_table,
    residual_table,
    strict_json,
    target_table,
    weighted_rms,
)
from pipeline.stages.identify.types import (
    AUTO_ORDER,
    DEFAULT_MODEL,
    IdentifyConfig,
    IdentifyResult,
    Robot,
    TooFewTouchups,
)
from pipeline.stages.parallel_map import parallel_map

#: the public names of identification, importable from here (its parts: this package)
__all__ = [
    "AUTO_ORDER",
    "COND_WARN",
    "DEFAULT_MODEL",
    "IdentifyConfig",
    "IdentifyResult",
    "TooFewTouchups",
    "best_result",
    "conditioning_note",
    "design_jacobian",
    "fit_outputs",
    "fit_prepared",
    "identify",
    "predicted_errors",
]


def identify(
    touchups: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    config: IdentifyConfig | None = None,
) -> IdentifyResult | dict[str, IdentifyResult]:
    """Identify kinematic corrections, the virtual pin and the targets from touch-ups.

    Parameters
    ----------
    touchups : DataFrame
        A touch-up table (``spec/touchups.md``; the touchups and
        inliers artefacts are ones). Rows used: ``converged`` (if the column
        exists), ``inlier`` (if it exists), ``weight > 0`` and finite joints.
    urdf : nominal URDF XML
    base_link, flange_link : the chain (``flange_link`` may be a tool link; its
        fixed joints stay nominal and the pin is found in its frame)
    config : IdentifyConfig

    Returns
    -------
    IdentifyResult, or ``{model name: IdentifyResult}`` for ``model="all"``.

    Raises
    ------
    BadInput
        Missing joint columns, unknown model, a distance naming an unknown target.
    CalibrationFailed
        No usable touch-ups, a single target without a known distance, all
        poses identical, or too few touch-ups for the model (says how many to add).
    """
    config = config or IdentifyConfig()
    robot = Robot.load(urdf, base_link, flange_link)
    if touchups.attrs:  # pandas deep-copies attrs on every operation; the fit reads none
        touchups = touchups.copy(deep=False)
        touchups.attrs = {}
    return fit_prepared(prepare_data(touchups, robot.chain, config), robot, config, touchups)


def fit_prepared(
    data: FitData,
    robot: Robot,
    config: IdentifyConfig,
    touchups: pd.DataFrame | None = None,
) -> IdentifyResult | dict[str, IdentifyResult]:
    """:func:`identify` from the table's rows as prepared: its one path after the table.

    Parameters
    ----------
    data : the rows of a touch-up table as :func:`pipeline.stages.identify.data.prepare_data`
        gives them (or :func:`pipeline.stages.identify.data.restrict`, for a subset of a
        table prepared once)
    robot : the nominal robot (URDF, chain base -> flange, its error models)
    config : IdentifyConfig
    touchups : the table ``data`` was prepared from, read by the plausibility guardrails
        (values of URDF joints outside the chain); needed when ``config.check_plausibility``

    Returns and raises as :func:`identify`.
    """
    chain, urdf = robot.chain, robot.urdf
    refuse_early(data, len(data.rows))
    implausible: list[str] = []
    if config.check_plausibility:
        if touchups is None:
            raise ValueError("fit_prepared: the plausibility guardrails need the touch-up table")
        implausible = implausible_rows(
            chain, data, touchups, urdf, chain.base_link, chain.tip_link, config
        )
    if implausible and not config.accept_implausible:
        raise CalibrationFailed(
            "implausible input: "
            + "; ".join(implausible)
            + " (rerun with --accept-implausible if it is right)"
        )
    data, frame = correction_frame(
        robot, data, config, lambda name, cfg: _identify_one(name, robot, data, cfg)
    )
    out = _identify_models(robot, data, config, implausible)
    for r in out.values() if isinstance(out, dict) else [out]:
        r.correction_map = frame.M
        if not config.prediction_only:
            r.summary["correction_frame"] = frame.summary
    return out


def _identify_models(
    robot: Robot,
    data: FitData,
    config: IdentifyConfig,
    implausible: list[str],
) -> IdentifyResult | dict[str, IdentifyResult]:
    """The model(s) ``config.model`` names (``all``, ``auto`` or one), fitted to ``data``."""
    if config.model == "all":

        def fit_one(name: str) -> IdentifyResult | str:
            try:
                return _identify_one(name, robot, data, config)
            except (BadInput, CalibrationFailed) as exc:
                return f"{name}: {exc}"

        names = model_names(robot.chain)
        if config.workers != 1:
            share_exact_touchups(robot)
        results: dict[str, IdentifyResult] = {}
        errors: list[str] = []
        for name, r in zip(names, parallel_map(fit_one, names, config.workers), strict=True):
            if isinstance(r, str):
                errors.append(r)
            else:
                results[name] = r
        if not results:
            raise CalibrationFailed("no error model could be identified: " + " | ".join(errors))
        for r in results.values():
            r.summary["other_models_failed"] = errors
            r.summary["implausible"] = implausible
        return results
    if config.model == "auto":
        refusals: list[str] = []
        for name in AUTO_ORDER:
            try:
                res = _identify_one(name, robot, data, config)
            except TooFewTouchups as exc:
                refusals.append(str(exc))
                continue
            res.summary["model_choice"] = f"auto: {name}" + (
                f" (fell back: {'; '.join(refusals)})" if refusals else ""
            )
            if refusals:
                res.summary["headline"].insert(1, f"model auto -> {name}: " + refusals[0])
            res.summary["implausible"] = implausible
            return res
        raise TooFewTouchups(" | ".join(refusals))
    one = _identify_one(config.model, robot, data, config)
    one.summary["implausible"] = implausible
    return one


@dataclass
class _Setup:
    """Step 1 of a fit: the problem, its scaling and the columns it identifies."""

    model: Any
    prob: Problem
    x0: F64
    pin0: F64
    tg0: F64
    Lc: float  # characteristic length (m): RMS distance of the targets from the base
    pscale: F64  # (P,) column scale
    st: Any  # the structural identifiability (:func:`structure`)
    kept: np.ndarray  # identified kinematic columns
    not_excited: np.ndarray  # structurally identifiable columns these touch-ups do not excite
    reasons: dict[int, str]  # held column -> why
    initial_rms: float  # m, at nominal kinematics


def _setup(name: str, robot: Robot, data: FitData, config: IdentifyConfig) -> _Setup:
    """Step 1: model, start point, scaling, identifiability; refuses too few touch-ups."""
    model, chain = robot.model(name), robot.chain
    x0 = model.zero()
    pin0, tg0 = initial_pin_targets(model, data, x0)
    prob = Problem(model, data, config)
    P, K, N = model.n_params, data.K, len(data.q)
    Lc = float(max(np.sqrt(np.mean(np.sum(tg0**2, axis=1))), 0.1))
    pscale = model.column_scale(Lc)  # column scale: J[:, j] * pscale[j]
    st = structure(
        name, robot.urdf, chain.base_link, chain.tip_link, bool(data.dist), float(config.rank_tol)
    )
    if st.gauge is not None:
        # the gauge row is defined in the structure's scaling; x_scaled = x * pscale
        g = st.gauge * model.column_scale(st.length)
        prob = Problem(model, data, config, gauge=g / np.linalg.norm(g))
    r0, J0 = prob.full_eval(x0, pin0, tg0)
    e0 = r0[: 3 * N].reshape(N, 3) / data.sw[:, None]
    initial_rms = float(np.sqrt(np.mean(np.sum(e0**2, axis=1))))
    assert J0 is not None
    Jn0 = J0[:, P:]
    reasons = dict(st.held)
    r_struct = len(st.kept)
    nuis_rank = int(np.linalg.matrix_rank(Jn0))
    rows_avail = prob.m - nuis_rank
    if rows_avail < r_struct + 3:
        need = math.ceil((r_struct + 3 - rows_avail) / 3)
        raise TooFewTouchups(
            f"model {name}: {N} usable touch-ups on {K} targets give {prob.m} equations; the "
            f"targets and the pin take {nuis_rank}, leaving {rows_avail} for the {r_struct} "
            f"kinematic parameters it identifies: add at least {need} more touch-up"
            + ("s" if need > 1 else "")
            + (" (or use --model offsets)" if name != "offsets" else "")
        )
    # what these touch-ups fail to excite among the structurally identifiable columns
    A = project_out(J0[:, st.kept] * pscale[st.kept], Jn0)
    k_loc, h_loc, _ = select_columns(A, config.data_tol)
    kept = st.kept[k_loc]
    for j in st.kept[h_loc]:
        reasons[int(j)] = "not excited by these touch-ups (add poses that vary this joint)"
    prob.free = kept
    return _Setup(
        model, prob, x0, pin0, tg0, Lc, pscale, st, kept, st.kept[h_loc], reasons, initial_rms
    )


@dataclass
class _Solved:
    """Step 2 of a fit: the solution and how it was reached."""

    sol: Any  # scipy OptimizeResult
    data: FitData  # with the print-shape levers applied when fitted
    shape: dict[str, Any] | None
    shape_fit: ShapeFit | None  # the fitted print shape, for touch-ups the fit has not seen
    noise_note: str
    sigma_flange: F64 | None
    method: str
    x: F64
    pin: F64
    tg: F64
    r: F64
    J: F64
    components: dict[str, Any] | None  # per-target variance components (identify.components)


def _solve(s: _Setup, data: FitData, config: IdentifyConfig) -> _Solved:
    """Step 2: least squares, flange-frame whitening (FGLS), print-shape refit."""
    prob, kept, N = s.prob, s.kept, len(data.q)
    z0 = prob.join(s.x0, s.pin0, s.tg0)
    xs = np.concatenate([1.0 / s.pscale[kept], np.ones(prob.layout.n_nuisance)])
    linear = config.robust_loss == "linear"
    method = "lm" if linear and prob.m >= z0.size else "trf"

    def solve(z_start: F64) -> Any:
        return least_squares(
            prob.fun,
            z_start,
            jac=prob.jac,
            method=method,
            loss=config.robust_loss if linear else partial_loss(config.robust_loss, 3 * N),
            f_scale=config.f_scale,
            x_scale=xs,
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            max_nfev=config.max_nfev,
        )

    sol = solve(z0)
    noise_note = "isotropic pin residuals in the base frame"
    sigma_flange = None
    if config.noise_model == "flange":
        # feasible generalised least squares: the touch-up error lives in the flange
        # (camera) frame, far larger along the view than across it; estimate its 3x3
        # covariance from the residuals and refit with them whitened.
        for _ in range(config.reweight_passes):
            W, sigma_flange = flange_whitening(prob, sol.x, len(kept))
            if W is None:
                break
            prob.W = W
            sol = solve(sol.x)
        if prob.W is not None:
            noise_note = (
                "pin residuals whitened by their covariance in the flange frame, estimated from "
                "the fit (feasible generalised least squares)"
            )
    shape: dict[str, Any] | None = None
    shape_fit: ShapeFit | None = None
    if data.shape_g is not None and config.target_shape != "none":
        sol, data, shape, shape_fit = fit_print_shape(prob, sol, solve, config, len(kept))
    sol, vc = weigh_targets(prob, sol, solve, config)
    data = prob.data if vc and vc["applied"] else data
    x, pin, tg = prob.split(sol.x)
    r, Jfull = prob.full_eval(x, pin, tg)
    assert Jfull is not None
    return _Solved(
        sol, data, shape, shape_fit, noise_note, sigma_flange, method, x, pin, tg, r, Jfull, vc
    )


def _uncertainty(s: _Setup, f: _Solved, config: IdentifyConfig) -> Uncertainty:
    """Step 3: covariance, correlations, observability and the predicted pin error."""
    prob, kept, model, data = s.prob, s.kept, s.model, f.data
    P = model.n_params
    Jfull = f.J
    Jz = Jfull[:, prob.columns()]
    zscale = np.concatenate([s.pscale[kept], np.ones(prob.layout.n_nuisance)])
    cov, sigma2, dof = covariance(Jz, zscale, f.r, spent_unknowns(prob.W, f.shape, f.components))
    std_z = np.sqrt(np.clip(np.diag(cov), 0, None))
    ne = len(kept) + 3
    cov_e = cov[:ne, :ne]
    de = np.sqrt(np.clip(np.diag(cov_e), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_e / np.outer(de, de)
    Ared = project_out(Jfull[:, :P][:, kept] * s.pscale[kept], Jfull[:, P:])
    obs = indices_from_singular_values(np.linalg.svd(Ared, compute_uv=False), prob.m)

    offset = config.pin_offset_cov_m2
    if offset is not None and f.shape is not None and f.shape.get("fitted"):
        S_res = flange_residual_cov(prob, f.sol.x, len(kept))
        offset = offset if S_res is None else pin_offset_left(offset, S_res)
    cov_e = with_pin_offset(cov_e, offset)
    rng = np.random.default_rng(config.seed)
    at = (model, f.x, f.pin, kept, cov_e)
    pred, spread = predicted_over(
        *at, workspace_poses(data.q, config.n_workspace, rng), spread=True
    )
    # (G1) of pipeline.estimation.region: just outside the covered joint ranges
    nom = model.nominal
    q_out = widened_poses(data.q, nom.lower, nom.upper, config.n_workspace, rng)
    pred["beyond"] = predicted_over(*at, q_out, ("shape",))[0]["shape"]
    return Uncertainty(std_z, corr, sigma2, int(dof), obs, pred, cov, spread)


def _identify_one(name: str, robot: Robot, data: FitData, config: IdentifyConfig) -> IdentifyResult:
    """Fit one error model, in steps: 1 set up and rate identifiability (:func:`_setup`),
    2 solve (:func:`_solve`), 3 uncertainty (:func:`_uncertainty`), 4 the three tables
    and the calibrated URDF, 5 the summary (:mod:`pipeline.stages.identify.tables`)."""
    t0 = time.perf_counter()
    s = _setup(name, robot, data, config)
    f = _solve(s, data, config)
    if config.prediction_only:
        return _prediction_only(name, s, f, t0)
    u = _uncertainty(s, f, config)
    model, kept, x, pin, tg = s.model, s.kept, f.x, f.pin, f.tg
    data = f.data
    norms_used = _pin_distances(model, f)
    fit = FitFigures(
        name=name,
        model=model,
        data=data,
        kept=kept,
        reasons=s.reasons,
        not_excited=[model.param_names[int(j)] for j in s.not_excited],
        n_structural=len(s.st.kept),
        x=x,
        pin=pin,
        pin0=s.pin0,
        tg=tg,
        norms_used=norms_used,
        shape=f.shape,
        noise_note=f.noise_note,
        components=f.components,
        sigma_flange=f.sigma_flange,
        sol=f.sol,
        method=f.method,
        loss=config.robust_loss,
        initial_rms=s.initial_rms,
        Lc=s.Lc,
    )
    summary = fit_summary(fit, u)
    summary["seconds"] = time.perf_counter() - t0
    return IdentifyResult(
        model=name,
        parameters=parameter_table(fit, u),
        residuals=residual_table(fit),
        targets=target_table(fit, u),
        calibrated_urdf=write_calibrated_urdf(
            robot.urdf, model.origins(x), robot.chain.tip_link, pin
        ),
        summary=summary,
        chain=model.chain(x),
        p_flange_pin=pin,
        x=x,
        error_model=model,
        target_xyz=_target_xyz(data, tg),
        print_shape=f.shape_fit,
        covariance=u.cov,
        covariance_names=covariance_names(model.param_names, kept, data.target_labels),
    )


def _target_xyz(data: FitData, tg: F64) -> dict[int, F64]:
    """``{target_id: (3,) fitted position}`` of the fit's targets ``tg`` (K, 3) m."""
    return {int(t): tg[k] for k, t in enumerate(data.target_ids)}


def _pin_distances(model: Any, f: _Solved) -> F64:
    """The pin-to-target distances of the used rows (residuals.parquet's), (N,) m.

    ``|T(q_i; x) (p_pin + d_i) - t_k|``, not the whitened residual vector the solver
    minimised: a fit residual in millimetres means a distance.
    """
    data = f.data
    p_used, _, _ = model.pin_and_jacobian(f.x, data.q, f.pin + data.d, jac=False)
    return np.asarray(np.linalg.norm(p_used - f.tg[data.tk], axis=1))


def _prediction_only(name: str, s: _Setup, f: _Solved, t0: float) -> IdentifyResult:
    """A fit for prediction alone (``IdentifyConfig.prediction_only``): what a held-out
    score needs, the model, pin and target positions, the residual RMS and the
    residual scale ``sigma = sqrt(|r|^2 / (m - p))`` (as :func:`covariance` has it),
    without the covariance, the tables and the URDF (about 30 % of a refit): the
    targets are :attr:`IdentifyResult.target_xyz` alone."""
    model, data = s.model, f.data
    sigma2, dof = residual_variance(
        f.r, len(s.prob.columns()) + spent_unknowns(s.prob.W, f.shape, f.components)
    )
    summary = {
        "rms_mm": weighted_rms(_pin_distances(model, f), data.sw) * 1e3,
        "sigma_mm": math.sqrt(sigma2) * 1e3 if dof > 0 else float("nan"),
        "n_identified": len(s.kept),
        "seconds": time.perf_counter() - t0,
    }
    return IdentifyResult(
        model=name,
        parameters=pd.DataFrame(),
        residuals=pd.DataFrame(),
        targets=pd.DataFrame(),
        calibrated_urdf="",
        summary=summary,
        chain=model.chain(f.x),
        p_flange_pin=f.pin,
        x=f.x,
        error_model=model,
        target_xyz=_target_xyz(data, f.tg),
        print_shape=f.shape_fit,
    )


# ----------------------------------------------------------------------------- output


def best_result(results: IdentifyResult | dict[str, IdentifyResult]) -> IdentifyResult:
    """The result whose ``calibrated.urdf`` a run ships: the default model if fitted, else
    the one with the smallest residual RMS."""
    if isinstance(results, IdentifyResult):
        return results
    if DEFAULT_MODEL in results:
        return results[DEFAULT_MODEL]
    return min(results.values(), key=lambda r: r.summary["rms_mm"])


def fit_outputs(results: IdentifyResult | dict[str, IdentifyResult]) -> dict[str, Any]:
    """What the identify stage writes, as data (the runner writes it).

    Returns
    -------
    dict with ``parameters``, ``residuals``, ``targets``: every model's rows in
    one table (``model`` column), as :class:`pipeline.io.run_folder.Parquet` with the
    :func:`best_result`'s ``scale_held`` and ``model`` in the metadata;
    ``model_urdfs``: ``{model: calibrated URDF text}``; ``models``: the JSON
    document ``{"models": {model: summary}, "order": [model, ...], "best_model": name}``
    (NaN as null; ``order``: the order the models were fitted, which headlines follow)
    from which the choose stage (:mod:`pipeline.stages.choose.stage`) makes identify.json.
    """
    from pipeline.io.run_folder import Parquet

    many = results if isinstance(results, dict) else {results.model: results}
    best = best_result(results)
    meta = {"scale_held": json.dumps(best.summary["scale_held"]), "model": best.model}
    tables = {
        key: Parquet(pd.concat([getattr(r, key) for r in many.values()], ignore_index=True), meta)
        for key in ("parameters", "residuals", "targets")
    }
    doc = {
        "models": {n: r.summary for n, r in many.items()},
        "order": list(many),  # the order fitted (JSON files sort their keys)
        "best_model": best.model,
    }
    return {
        **tables,
        "model_urdfs": {n: r.calibrated_urdf for n, r in many.items()},
        "models": strict_json(doc),
    }
