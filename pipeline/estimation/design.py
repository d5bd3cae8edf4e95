"""The identification Jacobian of planned touch-ups on the nominal robot (pose planning).

Eq. (1)'s Jacobian (:class:`pipeline.measurement.pin.Problem`) at nominal
kinematics for poses not measured yet, its structurally identifiable columns
(:func:`pipeline.estimation.identifiability.structure`) scaled to metres: what
:mod:`pipeline.plan.design` rates candidate poses with.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.estimation.identifiability import structure
from pipeline.kinematics.chain import load_chain
from pipeline.kinematics.se3 import F64
from pipeline.measurement.pin import Problem
from pipeline.models import make_model
from pipeline.stages.identify_data import prepare_data
from pipeline.stages.identify_types import DEFAULT_MODEL, IdentifyConfig


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
