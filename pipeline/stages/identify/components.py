"""Per-target variance components of a fit: weigh a target's touch-ups by their own scatter.

:mod:`pipeline.estimation.components` has the estimator (C1), the test (C2) and the
degrees of freedom they spend (C3). Here the groups are the targets: a touch-up's
three rows belong to its target; the known-distance and gauge rows to none. When
Bartlett's test rejects equal variances at
:data:`pipeline.estimation.components.COMPONENT_ALPHA`, each target's rows are
scaled by ``s / s_g`` (through the rows' square-root weights) and the fit redone,
until the factors settle (Helmert's iteration, at most :data:`PASSES` refits).

Weighing is asked for (``target_components="auto"``), not the default (``report``:
the factors and the test are reported, the fit is left as it is). Where the targets'
touch-ups differ in random scatter it pays (twelve simulated cells with one target's
touch-ups 6x noisier: the true error's RMS 0.321 -> 0.145 mm; the independent
generator's day 7 recording: 0.062 -> 0.058 mm absolute); where they differ by
systematic errors that look alike from pose to pose it costs (bench_optics seed 11,
LR Mate-like: sRGB 0.0157 -> 0.0244 mm, a declared vendor curve 0.0128 -> 0.0279 mm,
sRGB with output noise 0.0221 -> 0.0310 mm), and the test cannot tell the two apart
(p = 0.004 on day 7, 0.0036 on the sRGB cell).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from pipeline.estimation.components import COMPONENT_ALPHA, group_components
from pipeline.measurement.pin import Problem
from pipeline.stages.identify.types import IdentifyConfig

#: refits of Helmert's iteration at most
PASSES = 4
#: the iteration stops when every factor is within this of one
SETTLED = 0.02


def weigh_targets(
    prob: Problem, sol: Any, solve: Any, config: IdentifyConfig
) -> tuple[Any, dict[str, Any] | None]:
    """(C1)-(C3) over the targets; the refit solution where they were weighed apart.

    Parameters
    ----------
    prob : the fit's problem (its ``data.sw`` is replaced by the weighed rows' when applied)
    sol : the fit's solution (``sol.x``)
    solve : ``z_start -> OptimizeResult``, the fit's own solver
    config : ``target_components``: ``report`` (test and report, never weigh: the
        default), ``auto`` (weigh when the test rejects) or ``off`` (nothing)

    Returns
    -------
    sol : the solution (refitted when applied)
    components : None when ``off``; else (JSON-able) ``targets`` (labels), ``dof``,
        ``factor`` (C1) and ``bartlett``, ``p_value`` (C2) of the fit as it came,
        ``applied`` (bool), ``weights`` (per target, the factor its rows' weights were
        multiplied by), ``spent`` (C3)'s ``G - 1`` when applied, else 0
    """
    mode = config.target_components
    if mode == "off" or (mode == "report" and config.prediction_only):
        return sol, None  # nothing to do, or a report no one reads (cross-validation's refits)
    D0 = prob.data
    groups = np.full(prob.m, -1, dtype=int)
    groups[: 3 * len(D0.tk)] = np.repeat(np.asarray(D0.tk, dtype=int), 3)
    first = group_components(prob.jac(sol.x), prob.fun(sol.x), groups)
    out: dict[str, Any] = {
        "targets": list(D0.target_labels),
        **first,
        "alpha": COMPONENT_ALPHA,
        "applied": False,
        "weights": [1.0] * D0.K,
        "spent": 0,
    }
    p = first["p_value"]
    if config.target_components != "auto" or not (math.isfinite(p) and p < COMPONENT_ALPHA):
        return sol, out
    scale = np.ones(D0.K)
    for _ in range(PASSES):
        comp = group_components(prob.jac(sol.x), prob.fun(sol.x), groups)
        factor = np.array([f if math.isfinite(f) and f > 0 else 1.0 for f in comp["factor"]])
        if np.all(np.abs(factor - 1.0) < SETTLED):
            break
        scale /= np.sqrt(factor)
        scale /= math.exp(float(np.mean(np.log(scale))))  # geometric mean one
        prob.set_data(dataclasses.replace(D0, sw=D0.sw * scale[D0.tk]))
        sol = solve(sol.x)
    used = int(np.sum(np.isfinite(first["factor"])))
    out.update(applied=True, weights=(scale**2).tolist(), spent=max(used - 1, 0))
    return sol, out
