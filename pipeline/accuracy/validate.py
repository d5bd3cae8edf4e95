"""Accuracy of a calibration on touch-ups it was NOT fitted on (``vtcal validate``).

A second recording of the same cell touches targets whose positions are unknown.
A robot model (chain ``T_base_flange(q)`` and pin ``p``, flange frame) predicts
for touch-up ``i`` the point that touched its target (paper eq. 1, the
kinematics and the pin held)::

    x_i = R_i (p + d_i) + t_i,        (R_i, t_i) = T_base_flange(q_i)          (V1)

``d_i`` the touch-up's residual correction (flange frame, 0 when absent). All
touch-ups of one target touched the same point, so for a perfect model the
``x_i`` of a target coincide. Two figures need no ground truth and do not
depend on the base frame:

* **consistency**: per target ``k`` the centre ``c_k = mean_{i in k} x_i`` and
  ``sqrt(mean_i |x_i - c_{k(i)}|^2)``, pooled over every target (and per target);
  the same quantity as the held-out error of ``vtcal run`` (the distance of a
  predicted pin from its target), here on touch-ups of another recording;     (V2)
* **known-distance error**: ``| |c_a - c_b| - D |`` per known distance ``D``
  between targets ``a`` and ``b``: the length scale, which (V2) cannot see. (V3)

Robots judged: the calibrated one with its own pin (the headline), the
calibrated kinematics with the pin refitted on these touch-ups
(:func:`pipeline.measurement.pin.fit_pin_and_targets`: separates a pin error from a
kinematic one) and the nominal kinematics with a refitted pin (what the cell
gets without kinematic calibration; the "before"). The KPIs are those of
``benchmarks/bench_real.py`` (held-out placements of the MUKCa Panda data).
The refitted pins are fitted on the very touch-ups judged (unweighted), so
those two rows are optimistic by the pin's three degrees of freedom; the
calibrated robot's own pin is not.

Verdict (:func:`verdict`): improved when the headline consistency is below
:data:`pipeline.accuracy.verdict.IMPROVED_BELOW` times the nominal + refitted pin one
(:func:`pipeline.accuracy.verdict.improvement`, the rule of ``vtcal run``); with a
tolerance, PASS when improved, the consistency is at most the tolerance and
every known-distance error is at most the tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.accuracy.verdict import improvement
from pipeline.errors import BadInput, CalibrationFailed
from pipeline.estimation.correction_frame import (
    MAX_FRAME_DEVIATION,
    frame_deviation,
    table_scatters,
    translation_map,
)
from pipeline.io.numfmt import short
from pipeline.kinematics.chain import Chain, fk
from pipeline.kinematics.se3 import F64
from pipeline.kinematics.urdf import RobotDescription
from pipeline.kinematics.urdf_write import PIN_JOINT
from pipeline.measurement.pin import fit_pin_and_targets

#: a target needs this many usable touch-ups for a consistency (one point is always "consistent")
MIN_PER_TARGET = 2
#: row labels of the three robots judged
CALIBRATED = "calibrated (its own pin)"
CALIBRATED_REFIT = "calibrated + refitted pin"
NOMINAL_REFIT = "nominal + refitted pin"
#: the row of calibration.json's model where it is not the URDF's (followed by its name)
CALIBRATED_MODEL = "predictions' model:"


@dataclass(frozen=True)
class Touchups:
    """The usable touch-ups of the input: what is judged.

    Attributes
    ----------
    q : (N, n) joint vectors (rad, the chain's joint order)
    d : (N, 3) residual corrections, flange frame (m)
    tk : (N,) target index 0..K-1
    labels : K target labels (text), first-appearance order
    n_rows, n_unusable : rows of the input, rows not judged (rejected, not converged, ...)
    S : (N, 3, 3) the touch-ups' image-Jacobian pair scatters when the input has them
        (``pair_s**`` columns, :mod:`pipeline.estimation.correction_frame` F2), else None
    """

    q: F64
    d: F64
    tk: np.ndarray
    labels: list[str]
    n_rows: int
    n_unusable: int
    S: F64 | None = None

    @property
    def K(self) -> int:
        return len(self.labels)


def pin_of(robot: RobotDescription) -> tuple[str, F64] | None:
    """The flange link and the pin point (flange frame, m) of a calibrated URDF's ``virtual_pin_joint``.

    None when the URDF has no such joint (e.g. a nominal URDF).
    """
    j = robot.joints.get(PIN_JOINT)
    if j is None:
        return None
    return j.parent, np.asarray(j.T_parent_joint[:3, 3], dtype=float)


def _label(v: Any) -> str | None:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return None
    if isinstance(v, (int, np.integer)) or (isinstance(v, float) and v.is_integer()):
        return str(int(v))
    return str(v)


def usable_touchups(df: pd.DataFrame, joint_names: list[str], source: str) -> Touchups:
    """The rows of a touch-up table (``spec/touchups.md``) that are judged.

    A row is usable when it is converged and an inlier (where those columns exist,
    as in ``inliers.parquet``), its weight is positive (where given) and its joints
    and correction are finite.

    Raises
    ------
    BadInput
        A joint of the calibrated chain is not a column of the input, or a column is not numeric.
    CalibrationFailed
        A target has fewer than :data:`MIN_PER_TARGET` usable touch-ups, or none is usable.
    """
    missing = [j for j in joint_names if j not in df.columns]
    if "target_id" not in df.columns or missing:
        what = (
            f"joint(s) {missing} of the calibrated URDF are not in the input"
            if missing
            else "no target_id column"
        )
        cols = [c for c in df.columns if c not in ("touchup_id", "target_id")]
        raise BadInput(f"{source}: {what} (its columns: {cols[:12]}); is it the same robot?")
    try:
        q = df[joint_names].apply(pd.to_numeric, errors="raise").to_numpy(dtype=float)
        d = np.zeros((len(df), 3))
        for i, c in enumerate(("dx_flange", "dy_flange", "dz_flange")):
            if c in df.columns:
                d[:, i] = pd.to_numeric(df[c], errors="raise").to_numpy(dtype=float)
        w = (
            pd.to_numeric(df["weight"], errors="raise").to_numpy(dtype=float)
            if "weight" in df.columns
            else np.ones(len(df))
        )
    except (ValueError, TypeError) as exc:
        raise BadInput(
            f"{source}: a joint, correction or weight value is not a number: {exc}"
        ) from exc
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(d), axis=1) & (w > 0)
    for flag in ("converged", "inlier"):
        if flag in df.columns:
            ok &= df[flag].fillna(False).to_numpy(dtype=bool)
    labels = [_label(v) for v in df["target_id"].tolist()]
    ok &= np.array([lab is not None for lab in labels], dtype=bool)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        raise CalibrationFailed(f"{source}: none of its {len(df)} touch-ups is usable")
    order = list(dict.fromkeys(str(labels[i]) for i in idx))
    k_of = {lab: k for k, lab in enumerate(order)}
    tk = np.array([k_of[str(labels[i])] for i in idx], dtype=np.int64)
    counts = np.bincount(tk, minlength=len(order))
    few = [f"{order[k]} ({counts[k]})" for k in np.flatnonzero(counts < MIN_PER_TARGET)]
    if few:
        raise CalibrationFailed(
            f"{source}: target(s) {', '.join(few)} have fewer than {MIN_PER_TARGET} usable "
            "touch-ups: a consistency needs at least two per target (touch each target up "
            "again at other orientations)"
        )
    S = table_scatters(df)
    return Touchups(
        q[idx], d[idx], tk, order, len(df), len(df) - len(idx), None if S is None else S[idx]
    )


def predicted_points(chain: Chain, pin: F64, data: Touchups) -> F64:
    """(V1) ``x_i = R_i (p + d_i) + t_i`` in the base frame, (N, 3) m."""
    T = fk(chain, data.q)
    return np.asarray(np.einsum("nij,nj->ni", T[:, :3, :3], pin + data.d) + T[:, :3, 3])


def model_points(cal: Any, data: Touchups) -> F64:
    """(V1) with the forward map of a run's calibration.json model (:mod:`pipeline.use`):
    ``x_i = R_i (p + d_i) + t_i`` with ``(R_i, t_i)`` its flange pose (compliance included)."""
    p, _ = cal.pin_and_rotation(data.q, point=cal.p_flange_pin + data.d)  # per-row points
    return np.asarray(p)


def consistency(points: F64, tk: np.ndarray, K: int) -> tuple[F64, F64, F64]:
    """(V2): target centres and the distances of the points from their centre.

    Parameters
    ----------
    points : (N, 3) ; tk : (N,) target index ; K : number of targets

    Returns
    -------
    centres : (K, 3) ; dist : (N,) ``|x_i - c_k(i)|`` ; per_target_rms : (K,)
    """
    n = np.bincount(tk, minlength=K).astype(float)
    centres = np.stack([np.bincount(tk, points[:, c], minlength=K) for c in range(3)], 1)
    centres = centres / n[:, None]
    dist = np.linalg.norm(points - centres[tk], axis=1)
    per = np.sqrt(np.bincount(tk, dist**2, minlength=K) / n)
    return centres, dist, per


def known_distance_errors(
    centres: F64, labels: list[str], distances: list[tuple[str, str, float]]
) -> list[dict[str, Any]]:
    """(V3) per known distance ``(a, b, metres)`` (labels as text): measured and error, mm."""
    out = []
    for a, b, metres in distances:
        measured = float(np.linalg.norm(centres[labels.index(a)] - centres[labels.index(b)]))
        out.append(
            {
                "pair": f"{a}:{b}",
                "known_mm": metres * 1e3,
                "measured_mm": measured * 1e3,
                "error_mm": abs(measured - metres) * 1e3,
            }
        )
    return out


def judge(
    label: str,
    chain: Chain,
    pin: F64,
    data: Touchups,
    distances: list[tuple[str, str, float]],
    points: F64 | None = None,
) -> dict[str, Any]:
    """The figures of one robot (chain to the flange, pin in the flange frame) on ``data``.

    Returns
    -------
    dict: ``label``, ``pin_flange_m`` (3,), ``consistency_mm`` (pooled RMS, V2),
    ``max_mm``, ``per_target`` ``{label: {"n", "rms_mm"}}``, ``distances`` (V3 rows)
    and ``max_distance_error_mm`` (None without a known distance). ``points``: the
    (V1) points of a model a chain cannot hold (:func:`model_points`), else from ``chain``.
    """
    x = predicted_points(chain, pin, data) if points is None else points
    centres, dist, per = consistency(x, data.tk, data.K)
    counts = np.bincount(data.tk, minlength=data.K)
    rows = known_distance_errors(centres, data.labels, distances)
    return {
        "label": label,
        "pin_flange_m": [float(v) for v in pin],
        "consistency_mm": float(np.sqrt(np.mean(dist**2))) * 1e3,
        "max_mm": float(dist.max()) * 1e3,
        "per_target": {
            lab: {"n": int(counts[k]), "rms_mm": float(per[k]) * 1e3}
            for k, lab in enumerate(data.labels)
        },
        "distances": rows,
        "max_distance_error_mm": max((r["error_mm"] for r in rows), default=None),
    }


def refit_pin(chain: Chain, data: Touchups) -> F64:
    """The pin that best explains ``data`` at fixed kinematics (unweighted least squares)."""
    return fit_pin_and_targets(chain, data.q, data.d, data.tk, data.K)[0]


def match_distances(
    distances: list[tuple[int | str, int | str, float]], labels: list[str], source: str
) -> tuple[list[tuple[str, str, float]], list[str]]:
    """Known distances whose two targets were touched up, and notes for those dropped."""
    kept, dropped = [], []
    for a, b, metres in distances:
        sa, sb = str(a), str(b)
        absent = [s for s in (sa, sb) if s not in labels]
        if absent or sa == sb:
            why = f"no usable touch-up of target {absent[0]!r}" if absent else "same target"
            dropped.append(f"known distance {sa}:{sb}={metres:g} not judged: {why} in {source}")
        else:
            kept.append((sa, sb, float(metres)))
    return kept, dropped


def validate(
    calibrated: Chain,
    calibrated_pin: F64 | None,
    nominal: Chain,
    data: Touchups,
    distances: list[tuple[str, str, float]],
    tolerance_mm: float | None = None,
    model: Any = None,
) -> dict[str, Any]:
    """Judge a calibration, and the nominal robot, on touch-ups it was not fitted on.

    Parameters
    ----------
    calibrated : calibrated chain, base to flange
    calibrated_pin : (3,) its pin (flange frame, m); None: refitted here (then the
        headline is the refitted row, and says so)
    nominal : nominal chain, base to the same flange
    data : :func:`usable_touchups`
    distances : known distances ``(label a, label b, metres)`` between touched targets
    tolerance_mm : PASS / FAIL bound, mm (None: improved / not improved only)
    model : the run's :class:`pipeline.use.Calibration` when the model it predicts with is
        not the URDF's (``elastic``): judged too, on a row of its own after the URDF's

    Returns
    -------
    dict: ``robots`` (list of :func:`judge` dicts: calibrated, calibrated + refitted pin,
    nominal + refitted pin), ``headline`` (label of the robot judged), ``verdict``
    (``validated_mm``, ``nominal_mm``, ``ratio``, ``improved``, ``distance_error_mm``,
    ``tolerance_mm``, ``passed``, ``why``, ``line``), ``n_touchups``, ``n_unusable``,
    ``targets``, ``implausible`` (:func:`implausible`: the guardrail lines).

    The corrections are judged with the calibrated robot in its own flange frame,
    ``d_i -> M_eff d_i`` (:mod:`pipeline.estimation.correction_frame`, as identification
    fits them; not where the map is more than ``MAX_FRAME_DEVIATION`` off the identity,
    as identification does not), and as the table has them with the nominal robot.
    """
    import dataclasses

    M = translation_map(nominal, calibrated, data.q, S=data.S, p_point=calibrated_pin)
    if frame_deviation(M) > MAX_FRAME_DEVIATION:  # as identification: not a robot's map
        M = np.eye(3)
    data_c = dataclasses.replace(data, d=data.d @ M.T)
    refit_cal = judge(
        CALIBRATED_REFIT, calibrated, refit_pin(calibrated, data_c), data_c, distances
    )
    robots = []
    if calibrated_pin is not None:
        robots.append(judge(CALIBRATED, calibrated, calibrated_pin, data_c, distances))
    if model is not None:
        label = f"{CALIBRATED_MODEL} {model.model}"
        pts = model_points(model, data_c)
        robots.append(judge(label, calibrated, model.p_flange_pin, data_c, distances, pts))
    robots.append(refit_cal)
    before = judge(NOMINAL_REFIT, nominal, refit_pin(nominal, data), data, distances)
    robots.append(before)
    head = robots[0]
    v = _verdict(head, before, tolerance_mm, len(data.q), data.K)
    return {
        "implausible": implausible(nominal, data, distances),
        "robots": robots,
        "headline": head["label"],
        "verdict": v,
        "n_touchups": int(len(data.q)),
        "n_unusable": int(data.n_unusable),
        "targets": list(data.labels),
    }


def implausible(
    nominal: Chain, data: Touchups, distances: list[tuple[str, str, float]]
) -> list[str]:
    """The guardrails of identification (:mod:`pipeline.guardrails.plausibility`) on these touch-ups.

    Wherever a robot is judged, the same inputs are implausible: joint values
    outside the nominal URDF's limits, a nominal fit (pin and targets solved at
    nominal kinematics) worse than ``NOMINAL_RMS_MAX``, a known distance the
    nominal robot contradicts. On such touch-ups a "before" figure of 138 mm
    makes any calibration look thousands of times better; the verdict would
    mean nothing.

    Returns
    -------
    list of str : one line per implausible input (empty when plausible)
    """
    from pipeline.guardrails import plausibility as pl

    lines = pl.joint_values(data.q, nominal)
    _, targets, rho = pl.nominal_targets(
        nominal, data.q, data.d, data.tk, data.K, np.ones(len(data.q))
    )
    lines += pl.nominal_fit(rho)
    idx = {lab: k for k, lab in enumerate(data.labels)}
    known = [(idx[a], idx[b], m) for a, b, m in distances if a in idx and b in idx]
    lines += pl.known_distances(targets, rho, known, list(data.labels))
    return lines


def _verdict(
    head: dict[str, Any],
    before: dict[str, Any],
    tolerance_mm: float | None,
    n: int,
    K: int,
) -> dict[str, Any]:
    """PASS / FAIL and the one verdict line (rule in the module docstring)."""
    validated, nominal = head["consistency_mm"], before["consistency_mm"]
    ratio, improved = improvement(validated, nominal)
    dist_err = head["max_distance_error_mm"]
    how = f"held-out consistency ({n} touch-ups of {K} targets not fitted on"
    how += "; pin refitted on them)" if head["label"] == CALIBRATED_REFIT else ")"
    if improved:
        state = f"improved x{ratio:.1f} over the nominal robot's {nominal:.4f} mm ({NOMINAL_REFIT})"
    elif improved is False:
        state = f"NOT improved: the nominal robot's is {nominal:.4f} mm ({NOMINAL_REFIT})"
    else:
        state = "the nominal robot's consistency is unknown"
    line = f"verdict: calibrated robot: {validated:.4f} mm RMS {how}; {state}"
    if dist_err is not None:
        line += f"; known-distance error {dist_err:.4f} mm"
    passed, why = None, ""
    if tolerance_mm is not None:
        if validated > tolerance_mm:
            why = f"{validated:.4f} mm > {short(tolerance_mm)} mm"
        elif dist_err is not None and dist_err > tolerance_mm:
            why = f"known-distance error {dist_err:.4f} mm > {short(tolerance_mm)} mm"
        elif not improved:
            why = "not improved on the nominal robot"
        passed = not why
        if passed:
            why = f"{validated:.4f} mm <= {short(tolerance_mm)} mm"
            if dist_err is not None:
                why += f", known-distance error {dist_err:.4f} mm <= {short(tolerance_mm)} mm"
        line += f" | {'PASS' if passed else 'FAIL'} ({why})"
    elif not improved:
        why = "not improved on the nominal robot"
    return {
        "validated_mm": validated,
        "validated_max_mm": head["max_mm"],
        "validated_how": how,
        "nominal_mm": nominal,
        "ratio": ratio,
        "improved": improved,
        "distance_error_mm": dist_err,
        "tolerance_mm": tolerance_mm,
        "passed": passed,
        "why": why,
        "line": line,
    }


def refusal(result: dict[str, Any]) -> CalibrationFailed | None:
    """The exit-3 error of a validation that failed or did not improve (None when it did)."""
    v = result["verdict"]
    if v["passed"] is False or not v["improved"]:
        return CalibrationFailed(
            f"validate {'FAIL' if v['passed'] is False else 'NOT improved'}: {v['why']}"
        )
    return None
