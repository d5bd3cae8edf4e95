"""Which fitted model the run predicts with: the URDF's model, or one a URDF cannot carry.

``calibrated.urdf`` holds a rigid model (the smallest held-out error among the
models a URDF carries exactly, :func:`pipeline.stages.crossval.stage._choose`).
A model with configuration-dependent terms (``elastic``: joint compliance on
the gravity torque) can predict better than any rigid one, but only through
its own forward map: ``calibration.json`` carries it, and ``vtcal predict``,
``vtcal compensate`` and :func:`pipeline.use.load` use it.

The run predicts with such a model only when the held-out errors prefer it
beyond doubt, both conditions on the k-fold errors of the same touch-ups::

    rms_k(M) < (1 - TIE) rms_k(U)        and        z(M, U) <= -Z_APART           (P1)

``U`` the URDF's model, ``M`` the best-predicting model, ``rms_k`` the k-fold
RMS, ``z`` the paired test (T1) of :mod:`pipeline.accuracy.told_apart`
(negative: ``M`` misses less). Otherwise it predicts with ``U``, exactly what
``calibrated.urdf`` holds: a richer model is never taken on noise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from pipeline.accuracy.told_apart import Z_APART

#: the relative margin of (P1): the same 1 % tie rule as the URDF's choice
TIE = 0.01


def predict_choice(
    models: Mapping[str, Mapping[str, Any]],
    urdf_model: str | None,
    paired: Mapping[str, Mapping[str, Any]],
) -> tuple[str | None, str]:
    """The model the run predicts with, by (P1), and a sentence saying why.

    Parameters
    ----------
    models : cross-validation's figures per model (``kfold_rms_mm``,
        ``kfold_failed_folds``, ``urdf_exact``)
    urdf_model : the model ``calibrated.urdf`` carries (None: none chosen)
    paired : (T1) of every model against ``urdf_model``: ``{model: {"z": ...}}``

    Returns
    -------
    (model, sentence): ``urdf_model`` unless a model a URDF cannot carry passes (P1)
    """
    if urdf_model is None:
        return None, ""
    own = float(models[urdf_model].get("kfold_rms_mm", math.nan))
    rivals = {
        m: float(v["kfold_rms_mm"])
        for m, v in models.items()
        if m != urdf_model
        and not v.get("urdf_exact", True)
        and v.get("kfold_failed_folds", 1) == 0
        and math.isfinite(float(v.get("kfold_rms_mm") or math.nan))
    }
    if not rivals or not math.isfinite(own):
        return urdf_model, f"predictions use {urdf_model}, the model calibrated.urdf holds"
    best = min(rivals, key=lambda m: rivals[m])
    z = (paired.get(best) or {}).get("z")
    z = float(z) if isinstance(z, (int, float)) else math.nan
    ahead = rivals[best] < (1 - TIE) * own
    apart = math.isfinite(z) and z <= -Z_APART
    figures = f"held-out RMS {rivals[best]:.4f} mm against {own:.4f} mm, paired z = {z:+.1f}"
    if ahead and apart:
        return best, (
            f"predictions (calibration.json: vtcal predict, vtcal compensate) use {best}, "
            f"which predicts held-out touch-ups better than {urdf_model} ({figures}); "
            f"calibrated.urdf holds {urdf_model}, a rigid model (a URDF cannot carry "
            f"{best}'s configuration-dependent terms)"
        )
    if rivals[best] >= own:
        why = "no better on held-out touch-ups"
    elif not ahead:
        why = "better by no more than 1 %"
    else:
        why = f"not told apart (|z| < {Z_APART:g})"
    return urdf_model, (
        f"predictions use {urdf_model}, the model calibrated.urdf holds: {best} is "
        f"{why} ({figures})"
    )
