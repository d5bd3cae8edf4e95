"""The region a calibration holds for: the joint ranges its touch-ups covered, and beyond.

A calibration is validated where it was measured. Its error model predicts
everywhere, but the parameters the touch-ups determined only as combinations
that cancel inside the covered joint ranges can grow apart outside them (a
Kinova Gen3 lite calibrated on one placement was 9.2 mm off on others, against
6.9 mm for the nominal arm with a fitted pin). The covariance says
how much: the predicted shape error over poses drawn from the covered box
(:func:`pipeline.accuracy.evaluate.workspace_poses`) against poses from the box widened
by half its span on each side, clipped to the joint limits::

    growth = rms_pred(widened box) / rms_pred(covered box)                       (G1)

The report always names the covered ranges and (G1); above :data:`GROWTH_WARN`
it says the calibration is to be used inside the covered ranges only.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pipeline.estimation.spread import error_spread
from pipeline.estimation.uncertainty import field_errors, registered_field
from pipeline.kinematics.se3 import F64

#: predicted error just outside the covered ranges above this multiple of inside: said
#: (measured: 2.5-2.6 on the standard simulated cells, planned for the volume; 2.06 on one
#: placement of the real Panda data, whose other placements were about twice as far off)
GROWTH_WARN = 4.0


def joint_ranges(q: F64) -> tuple[F64, F64]:
    """Per joint the smallest and largest value the touch-ups took, (n,) each."""
    q = np.asarray(q, dtype=float)
    q = q[np.all(np.isfinite(q), axis=1)]
    return q.min(axis=0), q.max(axis=0)


def widened_poses(q: F64, lower: F64, upper: F64, n: int, rng: np.random.Generator) -> F64:
    """``n`` joint vectors uniform in the covered box widened by half its span each side.

    Clipped to the joint limits ``lower, upper`` (non-finite limits: no clip).
    """
    lo, hi = joint_ranges(q)
    span = hi - lo
    a, b = lo - 0.5 * span, hi + 0.5 * span
    a = np.where(np.isfinite(lower), np.maximum(a, lower), a)
    b = np.where(np.isfinite(upper), np.minimum(b, upper), b)
    out: F64 = a + (b - a) * rng.random((n, len(lo)))
    return out


def predicted_over(
    model: Any,
    x: F64,
    pin: F64,
    kept: np.ndarray,
    cov_e: F64,
    q: F64,
    kinds: tuple[str, ...] = ("shape", "absolute", "raw"),
    spread: bool = False,
) -> tuple[dict[str, F64], dict[str, dict[str, Any]]]:
    """Covariance-predicted pin errors (m) at the poses ``q`` (W, n), per registration kind.

    ``cov_e`` the covariance of the identified kinematic columns ``kept`` and the pin;
    :func:`pipeline.estimation.uncertainty.predicted_errors`'s propagation, each kind's
    registered field made once and shared with the spread. With
    ``spread``, also per kind how far one calibration's true RMS error may fall from the
    predicted RMS (:func:`pipeline.estimation.spread.error_spread`), else ``{}``.
    """
    p, R, J = model.pin_and_jacobian(x, q, pin, jac=True)
    assert J is not None
    Je = np.concatenate([J[:, :, kept], R], axis=2)
    fields = {kind: registered_field(Je, p, kind) for kind in kinds}
    pred = {kind: field_errors(G, cov_e) for kind, G in fields.items()}
    spreads = {kind: error_spread(G, cov_e) for kind, G in fields.items()} if spread else {}
    return pred, spreads


def region_summary(names: list[str], q: F64, inside_mm: float, beyond_mm: float) -> dict[str, Any]:
    """identify.json's ``region``: the covered ranges (deg), (G1) and a sentence."""
    lo, hi = joint_ranges(q)
    growth = beyond_mm / inside_mm if inside_mm > 0 else math.nan
    ranges = {
        n: [math.degrees(float(a)), math.degrees(float(b))]
        for n, a, b in zip(names, lo, hi, strict=True)
    }
    text = ", ".join(f"{n} {a:+.0f}..{b:+.0f} deg" for n, (a, b) in ranges.items())
    note = f"touch-ups covered {text}"
    if math.isfinite(growth) and growth > GROWTH_WARN:
        note += (
            f"; the predicted error grows {growth:.1f}x just outside these ranges "
            f"({beyond_mm:.4f} mm against {inside_mm:.4f} mm inside): use the calibration "
            "inside them, or measure where the robot works"
        )
    return {
        "joint_ranges_deg": ranges,
        "predicted_inside_mm": inside_mm,
        "predicted_beyond_mm": beyond_mm,
        "growth": growth,
        "extrapolation_warning": bool(math.isfinite(growth) and growth > GROWTH_WARN),
        "note": note,
    }
