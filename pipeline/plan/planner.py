"""The measuring-pose planner: candidates -> well-conditioned selection -> visiting order.

:func:`plan_poses` is the stage (pure: URDF text and targets in, plan table and
summary out). Steps: candidate views of every target solved by nominal IK
(:mod:`pipeline.plan.candidates`), their identification Jacobian reduced to
the identifiable directions (:mod:`pipeline.plan.design`), the exchange
selection by the chosen observability criterion (:mod:`pipeline.plan.select`),
and the visiting order (:mod:`pipeline.plan.order`). For comparison the same
number of poses drawn at random from the same candidates is rated too
("before").

Predicted post-calibration error: ``cov = sigma^2 S_e^-1`` of the kinematic
parameters and the pin (targets eliminated), ``sigma^2 = sigma_pin^2 +
sigma_enc^2 mean_i |J_v,i|_F^2 / 3`` (touch-up contact noise per axis plus
encoder noise carried to the pin), propagated to the pin over poses spread
through the candidates' joint-space box (:func:`pipeline.accuracy.evaluate.workspace_poses`)
and reduced by the best similarity registration (shape accuracy) as
identification predicts it. A covariance sees random error only.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.accuracy.evaluate import workspace_poses
from pipeline.errors import BadInput
from pipeline.kinematics.chain import Chain, jacobian, load_chain
from pipeline.kinematics.se3 import F64
from pipeline.plan.candidates import (
    REASONS,
    CandidateConfig,
    CandidateSet,
    generate_candidates,
    working_radius,
)
from pipeline.plan.design import Design, build_design
from pipeline.plan.order import order_visits, path_length, travel_costs
from pipeline.plan.select import CRITERIA, Selection, select_poses
from pipeline.plan.targets import PlanTargets


@dataclass(frozen=True)
class PlanConfig:
    """Planner settings (``vtcal plan`` options).

    Attributes
    ----------
    n_poses : measuring poses to choose
    n_candidates : candidate views over all targets
    cone_deg : largest angle between view axis and plate normal
    roll_deg : rolls about the view axis in ``+-roll_deg``
    p_flange_pin : virtual pin in the flange frame (approximate), m
    criterion : ``O1`` (D-optimal), ``O3``, ``O4`` or ``A``
    model : error model (:func:`pipeline.models.get_model`)
    seed : random seed (candidates, random comparison set, evaluation poses)
    sigma_m : touch-up contact noise per axis, m
    encoder_sigma_rad : encoder noise, rad
    n_seeds : IK seeds per candidate
    limit_margin_deg : required distance from joint limits
    min_dexterity : smallest inverse condition number of ``[J_v; L J_w]``
    switch_cost_rad : travel penalty of changing target
    n_eval : evaluation poses of the predicted error
    min_per_target : poses each target must get (so every target is measured)
    """

    n_poses: int = 36
    n_candidates: int = 2000
    cone_deg: float = 35.0
    roll_deg: float = 180.0
    p_flange_pin: tuple[float, float, float] = (0.0, 0.0, 0.2)
    criterion: str = "O1"
    model: str = "full"
    seed: int = 0
    sigma_m: float = 1e-5
    encoder_sigma_rad: float = 1e-6
    n_seeds: int = 6
    limit_margin_deg: float = 2.0
    min_dexterity: float = 0.02
    switch_cost_rad: float = 1.0
    n_eval: int = 200
    min_per_target: int = 2


@dataclass
class PlanResult:
    """A plan and what it was chosen from.

    Attributes
    ----------
    table : the plan (``schemas/plan.json``), rows in visiting order
    summary : JSON-able figures (indices before/after, predicted errors, counts, timings)
    candidates : every candidate with its accept/reject reason
    design : the candidates' reduced identification Jacobian
    selection : the exchange search's outcome
    """

    table: pd.DataFrame
    summary: dict[str, Any]
    candidates: CandidateSet
    design: Design
    selection: Selection
    eval_q: F64 = field(repr=False, default_factory=lambda: np.zeros((0, 0)))


def _check_config(c: PlanConfig) -> None:
    if c.n_poses < 1:
        raise BadInput(f"--poses {c.n_poses}: need at least one pose")
    if c.n_candidates < 1:
        raise BadInput(f"--candidates {c.n_candidates}: need at least one candidate")
    if not 0.0 < c.cone_deg <= 75.0:
        raise BadInput(
            f"--cone-deg {c.cone_deg}: must be in (0, 75] (the circle must stay a clear ellipse)"
        )
    if not 0.0 <= c.roll_deg <= 180.0:
        raise BadInput(f"--roll-deg {c.roll_deg}: must be in [0, 180]")
    if c.criterion not in CRITERIA:
        raise BadInput(f"--criterion {c.criterion!r}: use one of {', '.join(CRITERIA)}")
    if not c.sigma_m > 0:
        raise BadInput(f"--sigma-mm {c.sigma_m * 1e3}: must be positive")
    if not np.all(np.isfinite(c.p_flange_pin)) or np.linalg.norm(c.p_flange_pin) < 1e-3:
        raise BadInput(f"--pin {list(c.p_flange_pin)}: needs a stand-off of at least 1 mm")


def noise_sigma(chain: Chain, q: F64, p_flange_pin: F64, c: PlanConfig) -> float:
    """Per-axis pin noise of one touch-up: contact noise and encoder noise carried to the pin."""
    Jv = jacobian(chain, q, p_flange_pin)[:, :3]
    enc2 = c.encoder_sigma_rad**2 * float(np.mean(np.sum(Jv**2, axis=(1, 2)))) / 3.0
    return float(np.sqrt(c.sigma_m**2 + enc2))


def _refuse_unreachable(cs: CandidateSet, targets: PlanTargets, where: str) -> None:
    for k, tid in enumerate(targets.ids.tolist()):
        cnt = cs.counts[int(tid)]
        if cnt["accepted"] == 0:
            why = ", ".join(f"{r} {cnt[r]}" for r in REASONS if cnt[r])
            c = np.round(targets.centres[k], 3).tolist()
            raise BadInput(
                f"{where}: target {tid} at {c} m has no usable measuring pose among its "
                f"{cnt['candidates']} candidates ({why}); move it within reach or widen "
                "--cone-deg/--roll-deg"
            )


def plan_poses(
    urdf: str,
    targets: PlanTargets,
    config: PlanConfig,
    *,
    base_link: str = "base_link",
    flange_link: str = "flange",
    where: str = "targets",
) -> PlanResult:
    """Plan ``config.n_poses`` measuring poses (see module docstring).

    Parameters
    ----------
    urdf : nominal URDF XML
    targets : approximate target centres and plate normals (base frame)
    config : PlanConfig
    base_link, flange_link : the chain
    where : name of the targets' source for messages

    Returns
    -------
    PlanResult

    Raises
    ------
    BadInput
        Bad settings, unknown links or model, a target without any usable
        candidate, or fewer usable candidates than poses asked for.
    """
    _check_config(config)
    t_all = time.perf_counter()
    try:
        chain = load_chain(urdf, base_link, flange_link)
    except (KeyError, ValueError) as exc:
        raise BadInput(f"URDF chain {base_link} -> {flange_link}: {exc}") from None
    pin = np.asarray(config.p_flange_pin, dtype=float)
    t0 = time.perf_counter()
    cs = generate_candidates(chain, targets, _candidate_config(config, pin))
    t_cand = time.perf_counter() - t0
    _refuse_unusable(cs, targets, config, where)
    K = len(targets)
    L = working_radius(targets.centres)
    t0 = time.perf_counter()
    try:
        design = build_design(chain, config.model, cs.q, cs.target_index, K, pin, L)
    except KeyError as exc:
        raise BadInput(f"--model {config.model!r}: {exc.args[0]}") from None
    t_design = time.perf_counter() - t0

    sel = select_poses(design, config.n_poses, config.criterion, seed=config.seed)
    chosen = _ensure_per_target(design, sel.chosen, config, K)
    rating = _rate(chain, cs, design, chosen, pin, config)
    order, travel = _visiting_order(chain, cs, chosen, config)
    table = _plan_table(cs.accepted.iloc[chosen[order]].reset_index(drop=True), chain)

    seconds = {"candidates": t_cand, "design": t_design, "selection": sel.seconds}
    seconds["total"] = time.perf_counter() - t_all
    summary = _summary(
        f"{base_link} -> {flange_link}",
        chain,
        targets,
        config,
        table,
        cs,
        design,
        sel,
        rating,
        travel,
        seconds,
    )
    return PlanResult(
        table=table,
        summary=summary,
        candidates=cs,
        design=design,
        selection=sel,
        eval_q=rating["q_eval"],
    )


def _candidate_config(config: PlanConfig, pin: F64) -> CandidateConfig:
    """The candidate generator's settings from the planner's (angles in radians)."""
    return CandidateConfig(
        n_candidates=config.n_candidates,
        cone_rad=float(np.deg2rad(config.cone_deg)),
        roll_rad=float(np.deg2rad(config.roll_deg)),
        p_flange_pin=(float(pin[0]), float(pin[1]), float(pin[2])),
        n_seeds=config.n_seeds,
        limit_margin_rad=float(np.deg2rad(config.limit_margin_deg)),
        min_dexterity=config.min_dexterity,
        seed=config.seed,
    )


def _refuse_unusable(
    cs: CandidateSet, targets: PlanTargets, config: PlanConfig, where: str
) -> None:
    """Refuse (:class:`BadInput`) when no candidate is usable, a target has none, or fewer
    are usable than poses asked for."""
    n_ok = len(cs.q)
    if n_ok == 0:
        why = ", ".join(f"{r} {int((cs.table['reason'] == r).sum())}" for r in REASONS)
        raise BadInput(
            f"{where}: no usable measuring pose among {len(cs.table)} candidates ({why})"
        )
    _refuse_unreachable(cs, targets, where)
    if n_ok < config.n_poses:
        raise BadInput(
            f"--poses {config.n_poses}: only {n_ok} usable candidates; raise --candidates "
            "or lower --poses"
        )


def _rate(
    chain: Chain, cs: CandidateSet, design: Design, chosen: np.ndarray, pin: F64, c: PlanConfig
) -> dict[str, Any]:
    """The chosen poses and as many drawn at random from the same candidates ("before"):
    observability indices and predicted error of each (module docstring), with the
    evaluation poses ``q_eval`` and the pin noise ``sigma`` (m) the prediction used."""
    rng = np.random.default_rng(c.seed + 7919)
    random_set = rng.choice(len(design), c.n_poses, replace=False)
    rng_eval = np.random.default_rng(c.seed + 104729)
    q_eval = workspace_poses(cs.q, c.n_eval, rng_eval)
    sigma = noise_sigma(chain, cs.q, pin, c)
    before = design.indices(random_set)
    after = design.indices(chosen)
    pred_before = design.predicted_error(random_set, sigma, q_eval)
    pred_after = design.predicted_error(chosen, sigma, q_eval)
    return {
        "q_eval": q_eval,
        "sigma": sigma,
        "before": before,
        "after": after,
        "pred_before": pred_before,
        "pred_after": pred_after,
    }


def _visiting_order(
    chain: Chain, cs: CandidateSet, chosen: np.ndarray, config: PlanConfig
) -> tuple[np.ndarray, dict[str, float]]:
    """The visiting order of the chosen poses (positions into ``chosen``), and the joint
    travel (rad) grouped by target against ordered."""
    tk = cs.target_index[chosen]
    q_sel = cs.q[chosen]
    q_start = 0.5 * (np.maximum(chain.lower, -np.pi) + np.minimum(chain.upper, np.pi))
    order = order_visits(q_sel, tk, q_start=q_start, switch_cost=config.switch_cost_rad)
    D0 = travel_costs(q_sel, tk, 0.0)
    travel_before = path_length(D0, np.argsort(tk, kind="stable"))
    travel_after = path_length(D0, order)
    return order, {"grouped_by_target": travel_before, "ordered": travel_after}


def _plan_table(rows: pd.DataFrame, chain: Chain) -> pd.DataFrame:
    """The plan (``schemas/plan.json``) of the accepted candidates ``rows``, in their order."""
    table = pd.DataFrame(
        {
            "target_id": rows["target_id"].to_numpy(dtype=np.int64),
            "order": np.arange(len(rows), dtype=np.int64),
            "candidate_id": rows["candidate_id"].to_numpy(dtype=np.int64),
            "view_x": rows["view_x"].to_numpy(dtype=float),
            "view_y": rows["view_y"].to_numpy(dtype=float),
            "view_z": rows["view_z"].to_numpy(dtype=float),
            "tilt_rad": rows["tilt_rad"].to_numpy(dtype=float),
            "roll_rad": rows["roll_rad"].to_numpy(dtype=float),
            "dexterity": rows["dexterity"].to_numpy(dtype=float),
        }
    )
    for name in chain.joint_names:
        table[name] = rows[name].to_numpy(dtype=float)
    return table


def _summary(
    robot_chain: str,
    chain: Chain,
    targets: PlanTargets,
    config: PlanConfig,
    table: pd.DataFrame,
    cs: CandidateSet,
    design: Design,
    sel: Selection,
    rating: dict[str, Any],
    travel: dict[str, float],
    seconds: dict[str, float],
) -> dict[str, Any]:
    """The plan's JSON-able summary (:attr:`PlanResult.summary`)."""
    pin = np.asarray(config.p_flange_pin, dtype=float)
    per_target = {str(int(t)): int(np.sum(table["target_id"] == t)) for t in targets.ids.tolist()}
    return {
        "robot_chain": robot_chain,
        "joint_names": chain.joint_names,
        "n_poses": int(len(table)),
        "n_targets": int(len(targets)),
        "poses_per_target": per_target,
        "criterion": config.criterion,
        "model": config.model,
        "n_params": int(design.model.n_params),
        "n_identifiable": int(design.r),
        "p_flange_pin_m": [float(v) for v in pin],
        "pin_note": "approximate virtual pin (stand-off along the camera axis, flange z)",
        "candidates": {
            "total": int(len(cs.table)),
            "usable": int(len(cs.q)),
            "rejected": {r: int((cs.table["reason"] == r).sum()) for r in REASONS},
            "per_target": {str(k): v for k, v in cs.counts.items()},
        },
        "indices_before": rating["before"],
        "indices_after": rating["after"],
        "before_note": "the same number of poses drawn at random from the same candidates",
        "sigma_pin_mm": rating["sigma"] * 1e3,
        "predicted_before": {k: v * 1e3 for k, v in _mm(rating["pred_before"]).items()},
        "predicted_after": {k: v * 1e3 for k, v in _mm(rating["pred_after"]).items()},
        "predicted_shape_rms_mm": rating["pred_after"]["shape_rms_m"] * 1e3,
        "predicted_note": (
            "covariance-predicted pin error after calibration, over poses spread through the "
            "candidates' joint-space box, after the best similarity (shape) or rigid (absolute) "
            "registration; random error only"
        ),
        "selection": {
            "start_value": sel.start_value,
            "value": sel.value,
            "exchanges": sel.exchanges,
            "seconds": sel.seconds,
        },
        "travel_rad": travel,
        "seconds": seconds,
        "config": asdict(config),
    }


def _mm(d: dict[str, float]) -> dict[str, float]:
    return {(k[:-2] + "_mm" if k.endswith("_m") else k): v for k, v in d.items()}


def _ensure_per_target(design: Design, chosen: np.ndarray, config: PlanConfig, K: int) -> F64:
    """Give every target at least ``min_per_target`` poses (one pose on a target tells nothing:
    its position absorbs it), swapping in the D-best candidates of a short target for the
    poses whose removal costs least. Usually a no-op: the criterion already spreads poses."""
    from pipeline.plan.select import SelectionState, removal_values

    need = min(config.min_per_target, max(config.n_poses // K, 1))
    chosen = np.array(chosen, dtype=np.int64)
    for _ in range(K * need):
        counts = np.bincount(design.tk[chosen], minlength=K)
        short = np.flatnonzero(counts < need)
        if short.size == 0:
            break
        k = int(short[0])
        st = SelectionState(design, chosen.tolist(), 1e-12)
        cand = np.flatnonzero((design.tk == k) & ~np.isin(np.arange(len(design)), chosen))
        if cand.size == 0:
            break
        a = int(cand[int(np.argmax(st.add_gains(cand, "O1")))])
        plus = np.append(chosen, a)
        M = design.information(plus)
        rem = removal_values(design, M, plus, "O1")
        movable = counts[design.tk[plus]] > need
        movable[-1] = False
        if not movable.any():
            break
        rem[~movable] = -np.inf
        j = int(np.argmax(rem))
        chosen = np.delete(plus, j)
    return chosen
