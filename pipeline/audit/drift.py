"""How far the previous calibration is off on a new recording, in millimetres.

Per recording ``b`` after ``a`` of one robot, two figures:

* **validated** (``vtcal validate``'s, :func:`pipeline.accuracy.validate.validate`): the
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

* **the drift of the change read** (D3, :func:`read_drift_m`): the same figure
  for the change the test found and the cause it was read as; what ``vtcal
  audit`` reports as the drift (D1 when no single cause explains the change).

PASS when the drift and the validated consistency are at most the tolerance.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.accuracy.evaluate import pin_positions, registered_errors, workspace_poses
from pipeline.audit.attribute import Reading
from pipeline.audit.change import Difference
from pipeline.audit.fit import Estimate, point_columns
from pipeline.audit.identity import AuditItem
from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64

#: default PASS / FAIL tolerance, mm
TOLERANCE_MM = 0.1


def drift_m(
    old: tuple[Chain, F64], new: tuple[Chain, F64], q: F64, seed: int = 0, n: int = 0
) -> float:
    """(D1) between two robots ``(chain, pin)`` at the poses ``q`` (m); ``n > 0``: at ``n``
    poses drawn in their joint box instead (:func:`pipeline.accuracy.evaluate.workspace_poses`)."""
    qw = workspace_poses(q, n, np.random.default_rng(seed)) if n > 0 else np.asarray(q)
    pa = pin_positions(old[0], old[1], qw)
    pb = pin_positions(new[0], new[1], qw)
    return float(np.sqrt(np.mean(registered_errors(pa, pb, scale=False) ** 2)))


def validate_previous(
    prev: Estimate,
    fresh: Estimate,
    item: AuditItem,
    tolerance_mm: float = TOLERANCE_MM,
    read_mm: float = float("nan"),
) -> dict[str, Any]:
    """The previous calibration on ``item``'s touch-ups, beside its fresh one, and the drift.

    Parameters
    ----------
    read_mm : (D3) of the change read between the two, mm (NaN: none; (D1) is used)

    Returns
    -------
    dict: ``validated_mm`` (previous, consistency RMS), ``fresh_mm`` (fresh, same
    touch-ups), ``distance_error_mm`` (previous, worst known distance; None without),
    ``drift_raw_mm`` (D1), ``drift_mm`` ((D3) when given, else (D1)), ``passed``
    (drift and validated at most the tolerance), ``line``.
    """
    from pipeline.accuracy.validate import judge, match_distances, usable_touchups, validate
    from pipeline.kinematics import load_chain

    nominal = load_chain(item.urdf, item.base_link, item.flange_link)
    data = usable_touchups(item.table, list(nominal.joint_names), item.name)
    dist, _ = match_distances(item.distances, data.labels, item.name)
    res_p, res_f = prev.result, fresh.result
    v = validate(res_p.chain, res_p.p_flange_pin, nominal, data, dist, tolerance_mm)
    own = judge("fresh", res_f.chain, res_f.p_flange_pin, data, dist)
    old, new = (res_p.chain, res_p.p_flange_pin), (res_f.chain, res_f.p_flange_pin)
    raw_mm = drift_m(old, new, data.q) * 1e3
    d_mm = read_mm if np.isfinite(read_mm) else raw_mm
    validated = float(v["verdict"]["validated_mm"])
    passed = bool(d_mm <= tolerance_mm and validated <= tolerance_mm)
    return {
        "validated_mm": validated,
        "fresh_mm": float(own["consistency_mm"]),
        "distance_error_mm": v["verdict"].get("distance_error_mm"),
        "drift_mm": d_mm,
        "drift_raw_mm": raw_mm,
        "tolerance_mm": tolerance_mm,
        "passed": passed,
        "line": (
            f"{'PASS' if passed else 'FAIL'}: the previous calibration is {d_mm:.4f} mm off "
            f"(drift; {raw_mm:.4f} mm between the two calibrations with their noise) and "
            f"{validated:.4f} mm consistent on these touch-ups (fresh "
            f"{own['consistency_mm']:.4f} mm); tolerance {tolerance_mm:g} mm"
        ),
    }


def _rigid_residual(fresh: Estimate, J: F64) -> F64:
    """``P J``: the columns ``J`` (3N, k) of point motions with a rigid motion of the points
    projected out (the registration of (D1), linearised: translations and ``w x p_i``)."""
    model = fresh.result.error_model
    assert model is not None
    p, _, _ = model.pin_and_jacobian(fresh.result.x, fresh.q, fresh.result.p_flange_pin, jac=False)
    N = len(p)
    c = p - p.mean(axis=0)
    G = np.zeros((N, 3, 6))
    G[:, :, :3] = np.eye(3)
    z = np.zeros(N)
    G[:, :, 3:] = -np.stack(
        [z, -c[:, 2], c[:, 1], c[:, 2], z, -c[:, 0], -c[:, 1], c[:, 0], z], axis=1
    ).reshape(N, 3, 3)
    G2 = G.reshape(3 * N, 6)
    return np.asarray(J - G2 @ np.linalg.lstsq(G2, J, rcond=None)[0])


def read_drift_m(fresh: Estimate, diff: Difference, reading: Reading) -> float:
    """(D3) the drift of the change read (m).

    When a change was read as one cause, the pins move by ``J A_c beta`` (the
    change of the kinematic and pin quantities the cause explains, ``J`` their
    point derivatives at the fresh fit's poses); after the rigid registration::

        drift = sqrt(|P J A_c beta|^2 / N)                                     (D3)

    ``beta`` is many sigma when the test found it, so (D3) carries little of the
    two calibrations' noise, which (D1) carries whole (0.01-0.05 mm on the
    simulated cells: as large as a 0.1 mm link change's drift). A moved base
    leaves the robot as it was, and no change is no drift: 0. Several changes or
    different robots: NaN (then (D1) is the figure).
    """
    if reading.kind in ("none", "base"):
        return 0.0
    if not reading.explained:
        return float("nan")
    keep = [i for i, n in enumerate(diff.names) if not n.startswith("target.")]
    M = _rigid_residual(fresh, point_columns(fresh, [diff.names[i] for i in keep]))
    move = M @ np.asarray(reading.explained)[keep]
    return float(np.sqrt(np.sum(move**2) / len(fresh.q)))
