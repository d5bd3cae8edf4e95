"""How far the previous calibration is off on a new recording, in millimetres.

Per recording ``b`` after ``a`` of one robot, two figures:

* **validated** (``vtcal validate``'s, :func:`pipeline.validate.validate`): the
  previous calibration (its chain and its own pin) judged on ``b``'s touch-ups:
  the consistency RMS (V2) and known-distance errors (V3), against ``b``'s own
  fresh calibration judged on the same touch-ups (its training consistency);
* **drift**: what a user keeping the old calibration would see: the virtual pin
  the old and the fresh calibration predict at ``b``'s own touch-up poses (the
  poses the cell uses; over a box of joint ranges around them both calibrations
  extrapolate, and their own uncertainty, 0.03-0.08 mm on the simulated cell,
  would hide a 0.1 mm change), after the best-fit rigid motion (the base is
  never identified), RMS::

      drift = sqrt(mean_i |R p_old(q_i) + t - p_new(q_i)|^2)                 (D1)

  The truth's drift is (D1) with the true robots of ``a`` and ``b``
  (``benchmarks/bench_audit.py`` compares them).

PASS when the drift and the validated consistency are at most the tolerance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.audit.fit import Estimate
from pipeline.audit.identity import AuditItem
from pipeline.evaluate import pin_positions, registered_errors, workspace_poses
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64

#: default PASS / FAIL tolerance, mm
TOLERANCE_MM = 0.1


def drift_m(
    old: tuple[Chain, F64], new: tuple[Chain, F64], q: F64, seed: int = 0, n: int = 0
) -> float:
    """(D1) between two robots ``(chain, pin)`` at the poses ``q`` (m); ``n > 0``: at ``n``
    poses drawn in their joint box instead (:func:`pipeline.evaluate.workspace_poses`)."""
    qw = workspace_poses(q, n, np.random.default_rng(seed)) if n > 0 else np.asarray(q)
    pa = pin_positions(old[0], old[1], qw)
    pb = pin_positions(new[0], new[1], qw)
    return float(np.sqrt(np.mean(registered_errors(pa, pb, scale=False) ** 2)))


def validate_previous(
    prev: Estimate, fresh: Estimate, item: AuditItem, tolerance_mm: float = TOLERANCE_MM
) -> dict[str, Any]:
    """The previous calibration on ``item``'s touch-ups, beside its fresh one, and (D1).

    Returns
    -------
    dict: ``validated_mm`` (previous, consistency RMS), ``fresh_mm`` (fresh, same
    touch-ups), ``distance_error_mm`` (previous, worst known distance; None without),
    ``drift_mm`` (D1), ``passed`` (drift and validated at most the tolerance), ``line``.
    """
    from pipeline.kinematics import load_chain
    from pipeline.validate import judge, match_distances, usable_touchups, validate

    nominal = load_chain(item.urdf, item.base_link, item.flange_link)
    data = usable_touchups(item.table, list(nominal.joint_names), item.name)
    dist, _ = match_distances(item.distances, data.labels, item.name)
    res_p, res_f = prev.result, fresh.result
    v = validate(res_p.chain, res_p.p_flange_pin, nominal, data, dist, tolerance_mm)
    own = judge("fresh", res_f.chain, res_f.p_flange_pin, data, dist)
    d_mm = (
        drift_m((res_p.chain, res_p.p_flange_pin), (res_f.chain, res_f.p_flange_pin), data.q) * 1e3
    )
    validated = float(v["verdict"]["validated_mm"])
    passed = bool(d_mm <= tolerance_mm and validated <= tolerance_mm)
    return {
        "validated_mm": validated,
        "fresh_mm": float(own["consistency_mm"]),
        "distance_error_mm": v["verdict"].get("distance_error_mm"),
        "drift_mm": d_mm,
        "tolerance_mm": tolerance_mm,
        "passed": passed,
        "line": (
            f"{'PASS' if passed else 'FAIL'}: the previous calibration is {d_mm:.4f} mm off "
            f"(drift) and {validated:.4f} mm consistent on these touch-ups (fresh "
            f"{own['consistency_mm']:.4f} mm); tolerance {tolerance_mm:g} mm"
        ),
    }
