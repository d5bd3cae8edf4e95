"""The verdict of a run: the validated error of the shipped model, against the nominal robot.

A training residual is not an accuracy: it shrinks with every parameter fitted.
The verdict's headline is therefore the shipped model's **held-out** error
(k-fold cross-validation, ``crossval`` in identify.json), as an error of the
robot at new poses: a held-out touch-up misses by the calibration's error *and*
its own measurement error (:func:`own_noise_mm`), so the figure is

    validated = max(pred, sqrt((held^2 - e^2) (k - 1) / k))                        (V2)

the covariance-predicted error ``pred`` (absolute with a known distance, shape
without: :func:`predicted_kind`) (the random error the fit leaves,
valid when the model is adequate: :mod:`pipeline.stages.outliers.adequacy`) or, when the
held-out touch-ups miss by more than that beyond their own noise ``e``, that
(the ``(k-1)/k``: each fold's fit had that share of the touch-ups). The raw
held-out RMS overstated the error by up to 3.5x where the touch-ups' own noise
was comparable to the robot's error (bench_optics, docs/identification.md). Without
cross-validation it is the covariance-predicted error, labelled as such.
The covariance figure is an RMS expectation; one calibration's true error scatters
about it (a few parameter directions dominate it), so the line gives the range
(Q3) of :mod:`pipeline.estimation.spread` beside it.
It is compared with the nominal robot's error on the same touch-ups (the nominal
kinematics with their best pin and targets, ``solver.initial_rms_mm``). A run is
*improved* only when the validated error is below ``IMPROVED_BELOW`` times the
nominal one. Otherwise it says "not improved", and nothing is shown green.

Neither figure sees an error that the fit absorbs. When the model-adequacy test
or an assumption says one is likely (``identify.json["trust"]``,
:mod:`pipeline.stages.outliers.adequacy`), the line says the figure is a lower bound and a
tolerance fails.
"""

from __future__ import annotations

import math
from typing import Any

from pipeline.io.numfmt import short

#: a validated error at or above this share of the nominal robot's is "not improved"
IMPROVED_BELOW = 0.8
#: how the verdict line names the range (Q3) of :mod:`pipeline.estimation.spread`
RANGE_TEXT = "one calibration's true error 90 % within"


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else None


def improvement(
    validated_mm: float | None, nominal_mm: float | None
) -> tuple[float | None, bool | None]:
    """``(ratio, improved)``: nominal / validated and whether validated < IMPROVED_BELOW x nominal.

    Both None when either figure is unknown (or zero). The one rule of "improved", used by
    :func:`verdict` (a run) and :mod:`pipeline.accuracy.validate` (a calibration on a new recording).
    """
    if not nominal_mm or not validated_mm:
        return None, None
    return nominal_mm / validated_mm, bool(validated_mm < IMPROVED_BELOW * nominal_mm)


def own_noise_mm(summary: dict[str, Any]) -> float | None:
    """RMS of one touch-up's own error, mm: ``e^2 = rms_fit^2 3N / dof`` (V1).

    A held-out touch-up misses its prediction by the calibration's error at its pose
    *and* by its own measurement error, which is not the robot's. The fit's residual
    sum over its ``dof = 3N - p`` degrees of freedom estimates the latter's variance
    per component, ``3`` components per touch-up. None without those figures.
    """
    fit, n, dof = _num(summary.get("rms_mm")), _num(summary.get("n_rows")), _num(summary.get("dof"))
    if fit is None or n is None or dof is None or dof <= 0:
        return None
    return fit * math.sqrt(3.0 * n / dof)


def spread_mm(pred: float | None, spread: dict[str, Any]) -> list[float] | None:
    """The range (Q3) of one calibration's true RMS error, mm, or None where unknown.

    ``pred`` the covariance-predicted RMS (mm), ``spread`` identify.json's
    ``predicted_KIND_spread`` (:func:`pipeline.estimation.spread.error_spread`).
    """
    f = spread.get("range_factor") if pred is not None else None
    if not isinstance(f, list) or len(f) != 2 or _num(f[0]) is None or _num(f[1]) is None:
        return None
    return [float(pred) * float(f[0]), float(pred) * float(f[1])]  # type: ignore[arg-type]


def _predicted_text(pred: float | None, kind: str, span: list[float] | None) -> str:
    """The covariance figure as the line names it, with its range (Q3) where known."""
    text = f"{pred:.4f} mm {kind}" if pred is not None else ""
    if span is not None:
        text += f", {RANGE_TEXT} {span[0]:.4f}-{span[1]:.4f} mm"
    return text


def predicted_kind(summary: dict[str, Any]) -> str:
    """Which covariance-predicted figure the verdict takes: ``absolute`` or ``shape``.

    With a known distance the length scale is identified (``scale_held`` False) and the
    pin's error after a best-fit rigid motion (the base frame, never identifiable, is
    registered) is what a user meets: ``absolute``. It also carries the pin offset of
    (P1) (:func:`pipeline.estimation.uncertainty.with_pin_offset`), which a similarity
    partly hides. Without one the scale is a gauge and only ``shape`` applies.
    """
    return "absolute" if summary.get("scale_held") is False else "shape"


def tolerance_from_metadata(meta: dict[str, Any] | None) -> float | None:
    """The recording's ``tolerance_mm`` metadata key (mm) if it holds a positive number."""
    try:
        t = float((meta or {}).get("tolerance_mm", "nan"))
    except (TypeError, ValueError):
        return None
    return t if t > 0 else None  # NaN and <= 0: no tolerance


def verdict(
    summary: dict[str, Any] | None,
    tolerance_mm: float | None = None,
    nominal_mm: float | None = None,
) -> dict[str, Any] | None:
    """Validated error, fit residual, nominal error and the improvement, from identify.json.

    With ``tolerance_mm`` (``--tolerance-mm``, or the recording's ``tolerance_mm``
    metadata key) the run PASSES when its validated error is at most the tolerance
    and it improved on the nominal robot; it FAILS otherwise, also when nothing was
    validated. ``nominal_mm``: the nominal robot's error where the caller measured it
    (the report's nominal fit), else identify.json's ``solver.initial_rms_mm``.

    Returns
    -------
    None without a summary; else a dict: ``model``, ``validated_mm`` and ``validated_how``
    (held-out k-fold, or predicted), ``validated_max_mm``, ``fit_mm`` (training residual),
    ``predicted_mm`` with ``predicted_range_mm`` (the range (Q3) one calibration's true error
    falls in, :func:`spread_mm`), ``predicted_dof`` (Q2) and ``p_within_2x`` (Q4) of
    :mod:`pipeline.estimation.spread`, ``nominal_mm``, ``ratio`` (nominal / validated), ``improved`` (bool or
    None when unknown), ``tolerance_mm``, ``passed`` (None without a tolerance),
    ``lower_bound`` (the summary's ``trust`` found a systematic error likely or an
    assumption the figure hinges on: :mod:`pipeline.stages.outliers.adequacy`; a tolerance then
    fails), ``warnings`` (its console lines) and ``line`` (one sentence for the CLI).
    """
    if not summary:
        return None
    model = str(summary.get("best_model") or summary.get("model") or "")
    cv = ((summary.get("crossval") or {}).get("models") or {}).get(model) or {}
    held = _num(cv.get("kfold_rms_mm"))
    kind = predicted_kind(summary)
    pred = _num(summary.get(f"predicted_{kind}_rms_mm"))
    own = own_noise_mm(summary)
    spread = summary.get(f"predicted_{kind}_spread") or {}
    span = spread_mm(pred, spread)
    pred_text = _predicted_text(pred, kind, span)
    if held is not None and pred is not None and own is not None:
        k = float((summary.get("crossval") or {}).get("k") or 5)
        beyond = math.sqrt(max(held * held - own * own, 0.0) * (k - 1.0) / k)
        validated, vmax = max(pred, beyond), _num(cv.get("kfold_max_mm"))
        how = (
            f"held-out (k-fold, {cv.get('kfold_n', '?')} touch-ups: {held:.4f} mm each, "
            f"{beyond:.4f} mm less their own {own:.4f} mm noise; covariance-predicted "
            f"{pred_text})"
        )
    elif held is not None:
        validated, vmax = held, _num(cv.get("kfold_max_mm"))
        how = f"held-out (k-fold, {cv.get('kfold_n', '?')} touch-ups)"
    elif pred is not None:
        validated, vmax = pred, _num(summary.get(f"predicted_{kind}_max_mm"))
        how = f"predicted from the parameter covariance, {pred_text} (not cross-validated)"
    else:
        validated, vmax, how = None, None, "not available"
    initial = _num((summary.get("solver") or {}).get("initial_rms_mm"))
    nominal = nominal_mm if nominal_mm is not None else initial
    ratio, improved = improvement(validated, nominal)
    fit = _num(summary.get("rms_mm"))
    if validated is None:
        line = f"verdict: model {model}: no validated error (fit residual {fit} mm, training)"
    else:
        state = (
            f"improved x{ratio:.1f} over the nominal robot's {nominal:.4f} mm"
            if improved
            else (
                f"NOT improved: the nominal robot's error is {nominal:.4f} mm"
                if improved is False
                else "the nominal robot's error is unknown"
            )
        )
        fit_text = f"; fit residual {fit:.4f} mm (training)" if fit is not None else ""
        line = f"verdict: model {model}: {validated:.4f} mm RMS {how}; {state}{fit_text}"
    trust = summary.get("trust") or {}
    lower_bound = bool(trust.get("lower_bound"))
    if lower_bound:
        line += f" | {lower_bound_reason(trust)}: the figure is a lower bound"
    passed = None
    if tolerance_mm is not None:
        passed, why = _pass_fail(validated, tolerance_mm, improved, lower_bound)
        line += f" | {'PASS' if passed else 'FAIL'} ({why})"
    return {
        "tolerance_mm": tolerance_mm,
        "passed": passed,
        "model": model,
        "validated_mm": validated,
        "validated_max_mm": vmax,
        "validated_how": how,
        "fit_mm": fit,
        "predicted_mm": pred,
        "predicted_kind": kind,
        "predicted_range_mm": span,
        "predicted_dof": _num(spread.get("dof")),
        "p_within_2x": _num(spread.get("p_within_2x")),
        "nominal_mm": nominal,
        "ratio": ratio,
        "improved": improved,
        "lower_bound": lower_bound,
        "warnings": list(trust.get("warnings") or []),
        "line": line,
    }


def _pass_fail(
    validated: float | None, tolerance_mm: float, improved: bool | None, lower_bound: bool
) -> tuple[bool, str]:
    """PASS (validated <= tolerance, improved, not a lower bound) or FAIL, and why."""
    if validated is None:
        return False, "nothing validated"
    if validated > tolerance_mm:
        return False, f"{validated:.4f} mm > {short(tolerance_mm)} mm"
    if not improved:
        return False, "not improved on the nominal robot"
    if lower_bound:
        return False, "the figure is a lower bound"
    return True, f"{validated:.4f} mm <= {short(tolerance_mm)} mm"


def lower_bound_reason(trust: dict[str, Any]) -> str:
    """Why a run's figure is a lower bound, a few words (:mod:`pipeline.stages.outliers.adequacy`)."""
    if (trust.get("adequacy") or {}).get("systematic"):
        return "systematic error likely"
    keys = [str(a.get("key")) for a in trust.get("assumptions") or [] if a.get("lower_bound")]
    return "doubtful " + ", ".join(keys) if keys else "systematic error possible"
