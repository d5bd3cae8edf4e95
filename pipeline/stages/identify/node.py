"""The identify stage's node: inliers in, every asked-for model's fit out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

from pipeline.io.run_folder import parquet_meta


def identify(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """Every asked-for error model fitted: the three tables, models.json, one URDF per model.

    With the touch-ups stage in the run, the target diameter its image Jacobian implies
    (their ``implied_target_diameter_m`` metadata) is checked by the guardrails, and the
    covariance of their pose component (``capture_noise``) enters the predicted errors as
    the pin offset no residual sees (:func:`pipeline.estimation.uncertainty.with_pin_offset`).
    """
    from pipeline.stages.identify import stage
    from pipeline.stages.touchups.noise import pin_offset_cov

    urdf, base_link, flange_link = context.robot
    if "touchups" in data:
        tu = parquet_meta(data, "touchups")
        implied = _finite(tu.get("implied_target_diameter_m"))
        # the pose component's unseen mean: a pin offset in the predicted errors (P1)
        pose = pin_offset_cov(json.loads(tu.get("capture_noise") or "{}"))
        config = dataclasses.replace(
            config, implied_target_diameter_m=implied, pin_offset_cov_m2=pose
        )
    results = stage.identify(data["inliers"], urdf, base_link, flange_link, config)
    return stage.fit_outputs(results)


def _finite(text: str | None) -> float | None:
    """A metadata number, None when absent, not a number or not finite."""
    try:
        value = float(text) if text else float("nan")
    except ValueError:
        return None
    return value if math.isfinite(value) else None
