"""The identify stage's node: inliers in, every asked-for model's fit out.

Called by the runner as declared in :data:`pipeline.run.catalog.STAGES`: the
artefacts the stage reads (``data``), its options and the run's context
(:class:`pipeline.run.runner.Context`) in, ``{artefact key: value}`` out for the
runner to write; nothing here writes a file. The stage's computation is
imported inside the function, so importing this module stays cheap (the catalog
imports it) and a function replaced at run time is the one that runs (and the one
the stage code key hashes, :mod:`pipeline.run.code_key`).
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
