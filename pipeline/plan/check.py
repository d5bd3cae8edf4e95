"""Measuring what a pose set buys: synthetic touch-ups at given poses, identification, accuracy.

Used by the planner's benchmark (``benchmarks/bench_plan.py``) and tests. A
*true* robot (nominal + deviations, :func:`pipeline.accuracy.evaluate.perturbed_chain`)
and a true pin are touched up at the planned poses: from each planned joint
vector the true pin is pulled onto the true target plus an isotropic contact
miss ``N(0, noise_pin_m^2)`` per axis by minimum-norm Gauss-Newton on the pin
position (:func:`pipeline.accuracy.evaluate.solve_pin_ik`, as the servo loop moves the
flange, orientation kept near the plan), the recorded joints get encoder noise
``N(0, noise_q_rad^2)``; the table goes through the real identification
(:func:`pipeline.stages.identify.stage.identify`) and the calibrated chain and pin
are scored by :func:`pipeline.accuracy.evaluate.pin_accuracy`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from pipeline.accuracy.evaluate import pin_accuracy, solve_pin_ik
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64


def touchups_at(
    chain_true: Chain,
    p_pin_true: ArrayLike,
    targets_true: ArrayLike,
    q_plan: ArrayLike,
    target_index: ArrayLike,
    rng: np.random.Generator,
    *,
    noise_pin_m: float = 1e-5,
    noise_q_rad: float = 1e-6,
) -> pd.DataFrame:
    """A touch-up table (``pipeline.stages.identify.stage`` input) of the true robot at planned poses.

    Parameters
    ----------
    chain_true : true chain, base to flange
    p_pin_true : (3,) true virtual pin, flange frame
    targets_true : (K, 3) true target centres, base frame
    q_plan : (N, n) planned joint vectors (the IK seeds)
    target_index : (N,) target of each pose, 0..K-1
    rng : noise generator
    noise_pin_m, noise_q_rad : contact miss per axis, encoder noise

    Returns
    -------
    DataFrame ``touchup_id, target_id``, one column per joint, ``dx/dy/dz_flange``,
    ``weight``, ``converged`` (False where the true pin could not be put on the target)
    """
    q_plan = np.asarray(q_plan, dtype=float)
    tk = np.asarray(target_index, dtype=np.int64)
    tg = np.asarray(targets_true, dtype=float)[tk]
    miss = rng.normal(0.0, noise_pin_m, tg.shape)
    q, ok = solve_pin_ik(chain_true, p_pin_true, tg + miss, q_plan)
    q = q + rng.normal(0.0, noise_q_rad, q.shape)
    df = pd.DataFrame(q, columns=chain_true.joint_names)
    df.insert(0, "target_id", tk)
    df.insert(0, "touchup_id", np.arange(len(df), dtype=np.int64))
    for c in ("dx_flange", "dy_flange", "dz_flange"):
        df[c] = 0.0
    df["weight"] = 1.0
    df["converged"] = ok
    return df


def calibrate_and_score(
    table: pd.DataFrame,
    urdf: str,
    chain_true: Chain,
    p_pin_true: ArrayLike,
    q_eval: ArrayLike,
    *,
    model: str = "full",
    base_link: str = "base_link",
    flange_link: str = "flange",
) -> dict[str, Any]:
    """Identify from a touch-up table and score against the truth over ``q_eval``.

    Returns
    -------
    dict: ``shape_rms_m`` etc. (:func:`pipeline.accuracy.evaluate.pin_accuracy`), ``identify_predicted_
    shape_rms_m`` (identification's own covariance prediction) and ``n_identified``
    """
    from pipeline.stages.identify.stage import IdentifyConfig, identify

    res = identify(table, urdf, base_link, flange_link, IdentifyConfig(model=model))
    assert not isinstance(res, dict)
    acc = pin_accuracy(res.chain, res.p_flange_pin, chain_true, p_pin_true, q_eval)
    acc["identify_predicted_shape_rms_m"] = float(res.summary["predicted_shape_rms_mm"]) * 1e-3
    acc["n_identified"] = int(res.summary["n_identified"])
    return acc


def true_world(
    chain: Chain,
    p_pin: ArrayLike,
    centres: ArrayLike,
    rng: np.random.Generator,
    *,
    xyz_m: float = 5e-4,
    rpy_rad: float = 1.5e-3,
    q0_rad: float = 1e-3,
    pin_m: float = 2e-3,
) -> tuple[Chain, F64, F64]:
    """A true robot (uniform deviations of the simulator's size), a true pin a few mm from the
    assumed one and the true targets where that pin lands at the planned centres.

    Returns
    -------
    chain_true, p_pin_true (3,), targets_true (K, 3)
    """
    from pipeline.accuracy.evaluate import perturbed_chain, random_deviations

    dev = random_deviations(chain, rng, xyz_m=xyz_m, rpy_rad=rpy_rad, q0_rad=q0_rad)
    chain_true = perturbed_chain(chain, dev)
    pin_true = np.asarray(p_pin, dtype=float) + rng.uniform(-pin_m, pin_m, 3)
    return chain_true, pin_true, np.asarray(centres, dtype=float).copy()
