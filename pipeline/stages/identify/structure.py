"""Structural identifiability of identify's error models, and the planning Jacobian.

What a model can identify from touch-ups of a robot at all (:func:`structure`:
rated on exact synthetic touch-ups of the nominal robot, :func:`exact_touchups`,
through the pivoted QR of :mod:`pipeline.estimation.identifiability`), and eq.
(1)'s Jacobian at nominal kinematics for poses not measured yet, reduced to those
columns and scaled to metres (:func:`design_jacobian`). Both prepare their
touch-ups as identify does (:func:`pipeline.stages.identify.data.prepare_data`),
so they sit with the stage, above :mod:`pipeline.estimation`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pandas as pd

from pipeline.errors import CalibrationFailed
from pipeline.estimation.identifiability import held_reasons, select_columns
from pipeline.kinematics.chain import load_chain
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.measurement.pin import Problem
from pipeline.models import make_model
from pipeline.models.observability import project_out
from pipeline.stages.identify.data import prepare_data
from pipeline.stages.identify.types import DEFAULT_MODEL, IdentifyConfig, Robot


@dataclass(frozen=True)
class Structure:
    """What a model can identify from touch-ups of this robot at all."""

    kept: np.ndarray  # columns identified, sorted
    held: dict[int, str]  # column -> reason
    gauge: F64 | None  # (P,) scale-gauge row (scaled units), None if the scale is identified
    length: float  # characteristic length of the scaling the gauge was built in


@lru_cache(maxsize=64)
def structure(
    name: str, urdf: str, base_link: str, flange_link: str, has_dist: bool, tol: float
) -> Structure:
    """Structural identifiability from exact synthetic touch-ups of the nominal robot.

    Redundancies are exact only where the residuals vanish (a base rotation turns
    a residual vector; a uniform scale shrinks it), so they are found on exact
    touch-ups of the nominal robot: 3 targets x 15 poses spread over the joint
    ranges, with a known distance, the Jacobian (scaled, pin and targets
    projected out) through a pivoted QR. Without a known distance one more
    direction is unidentifiable, the uniform scale: the model-parameter
    direction ``v`` that, with the pin and targets, scales every pin position
    (least squares of ``J_x v + J_pin w = p``). It is held by the gauge
    constraint ``v . x_scaled = 0`` (the fit has no component along the scale
    of the nominal robot) instead of holding one arbitrary length. Cached per
    robot and model.
    """
    chain = load_chain(urdf, base_link, flange_link)
    model = make_model(name, chain)
    data, tg, p_c = exact_touchups(urdf, base_link, flange_link)
    prob = Problem(model, data, IdentifyConfig(distance_weight=1.0))
    P = model.n_params
    _, J = prob.full_eval(model.zero(), p_c, tg)
    assert J is not None
    Lc = float(np.sqrt(np.mean(np.sum(tg**2, axis=1))))
    pscale = model.column_scale(Lc)
    prio = model.param_priority
    A = project_out(J[:, :P] * pscale, J[:, P:])
    kept, held, _ = select_columns(A * prio, tol)
    reasons = held_reasons(A, kept, held, model.param_names, tol)
    gauge = None
    if not has_dist:
        # scale: the direction that leaves every touch-up row unchanged but stretches the
        # distance between targets 0 and 1 (J_x v + J_pin w + J_t u = 0, d|t0 - t1| = 1)
        N = len(data.q)
        B = np.concatenate([J[:, kept] * pscale[kept], J[:, P:]], axis=1)
        rhs = np.zeros(B.shape[0])
        rhs[3 * N] = 1.0
        sol = np.linalg.lstsq(B, rhs, rcond=None)[0]
        fit = np.linalg.norm(B @ sol - rhs)
        v = sol[: len(kept)]
        if fit < 1e-6 and np.linalg.norm(v) > 0:
            gauge = np.zeros(P)
            gauge[kept] = v / np.linalg.norm(v)
    return Structure(kept=kept, held=reasons, gauge=gauge, length=Lc)


@lru_cache(maxsize=16)
def exact_touchups(urdf: str, base_link: str, flange_link: str) -> tuple[FitData, F64, F64]:
    """The exact synthetic touch-ups :func:`structure` rates every model on, (data, targets, pin).

    3 targets x 15 poses of the nominal robot, spread over the joint ranges (around the
    zero pose, else around mid-range), with a known distance between targets 0 and 1
    of 1 m; ``targets`` (3, 3) m and the pin ``p_flange_pin`` (3,) m they touch. They
    depend on the robot alone, not on the error model, so they are made once per
    robot and process (their inverse kinematics is most of a model's rating) and
    shared by every model's :func:`structure`.
    """
    from pipeline.accuracy.evaluate import synthetic_touchups

    chain = load_chain(urdf, base_link, flange_link)
    rng = np.random.default_rng(20240601)
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    p_c = np.array([0.013, -0.009, 0.15])
    for centre in (np.clip(0.0, lo, hi), 0.5 * (lo + hi)):
        table, tg = synthetic_touchups(
            chain, p_c, 3, 15, rng, q_centre=centre, centre_spread_rad=0.8
        )
        if len(table) >= 36 and table["target_id"].nunique() == 3:
            break
    if len(table) < 12 or table["target_id"].nunique() < 2:
        raise CalibrationFailed(
            f"cannot place exact touch-ups on the nominal robot {base_link} -> "
            f"{flange_link} to rate identifiability (joint limits too tight?)"
        )
    data = prepare_data(table, chain, IdentifyConfig(distances=[(0, 1, 1.0)]))
    return data, tg, p_c


def design_jacobian(
    urdf: str,
    base_link: str,
    flange_link: str,
    q: F64,
    target_ids: np.ndarray,
    p_flange_pin: F64,
    *,
    model: str = DEFAULT_MODEL,
    known_distance: bool = False,
) -> tuple[F64, F64, list[str]]:
    """Identification Jacobian of planned touch-ups on the nominal robot (for pose planning).

    Parameters
    ----------
    urdf, base_link, flange_link : the nominal chain
    q : (N, n) planned converged joint vectors
    target_ids : (N,) which target each touches (any labels)
    p_flange_pin : (3,) the (expected) virtual pin
    model : error model whose structurally identifiable parameters are rated
    known_distance : add a distance row between the first two targets

    Returns
    -------
    J_kin : (m, L) scaled columns of the identifiable kinematic parameters
        (radians times the working radius, so every column is in metres)
    J_nuisance : (m, 3 + 3K) pin and target columns
    names : the L parameter names

    ``pipeline.models.observability.observability(J_kin, J_nuisance)`` rates the set.
    """
    chain = load_chain(urdf, base_link, flange_link)
    labels = list(dict.fromkeys(np.asarray(target_ids).tolist()))
    table = pd.DataFrame(np.asarray(q, dtype=float), columns=chain.joint_names)
    table.insert(0, "target_id", [labels.index(t) for t in np.asarray(target_ids).tolist()])
    table.insert(0, "touchup_id", np.arange(len(table)))
    dist: list[tuple[int | str, int | str, float]] = (
        [(0, 1, 1.0)] if known_distance and len(labels) > 1 else []
    )
    data = prepare_data(table, chain, IdentifyConfig(distances=dist))
    m = make_model(model, chain)
    pin = np.asarray(p_flange_pin, dtype=float)
    p, _, _ = m.pin_and_jacobian(m.zero(), data.q, pin, jac=False)
    tg = np.array([p[data.tk == k].mean(axis=0) for k in range(data.K)])
    st = structure(model, urdf, base_link, flange_link, bool(dist), IdentifyConfig().rank_tol)
    Lc = float(max(np.sqrt(np.mean(np.sum(tg**2, axis=1))), 0.1))
    pscale = m.column_scale(Lc)
    prob = Problem(m, data, IdentifyConfig())
    _, J = prob.full_eval(m.zero(), pin, tg)
    assert J is not None
    P = m.n_params
    return J[:, st.kept] * pscale[st.kept], J[:, P:], [m.param_names[int(j)] for j in st.kept]


def share_exact_touchups(robot: Robot) -> None:
    """Make the robot's exact synthetic touch-ups here, before the fits fork.

    Every model's structural identifiability (:func:`structure`) rates it on the same
    exact touch-ups (:func:`exact_touchups`, cached
    per process); made once in this process, the forked workers (and a later stage's)
    find them made instead of each solving their inverse kinematics again. When they
    cannot be made, each model's fit says so.
    """
    chain = robot.chain
    try:
        exact_touchups(robot.urdf, chain.base_link, chain.tip_link)
    except CalibrationFailed:
        pass
