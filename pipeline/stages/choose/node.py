"""The choose stage's node: the fitted models in, the shipped ones out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

import json
from typing import Any

from pipeline.io.run_folder import parquet_meta


def choose(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """calibrated.urdf, calibration.json and identify.json: the shipped models.

    :mod:`pipeline.stages.choose.stage` picks the URDF's model,
    :mod:`pipeline.use.record` records the model predictions use.
    """
    from pipeline.stages.choose import stage
    from pipeline.stages.outliers.adequacy import trust
    from pipeline.use.record import calibration_record

    # the cross-validation summary and the capture noise ride in their tables' metadata
    summary = json.loads(parquet_meta(data, "crossval")["summary"]) if "crossval" in data else None
    urdf, shipped = stage.choose_model(data["models"], data["model_urdfs"], summary, context.source)
    tu = parquet_meta(data, "touchups") if "touchups" in data else None
    noise = json.loads(tu.get("capture_noise") or "{}") if tu is not None else None
    rec = data.get("recording")
    shipped["trust"] = trust(shipped, noise, rec if isinstance(rec, dict) else None)
    record = calibration_record(
        data["parameters"], data["models"], summary, context.robot, str(shipped["best_model"])
    )
    shipped["predict_model"] = record["model"]
    shipped["predict_choice"] = record["choice"]
    if summary is not None:  # the choice for predictions, beside the URDF's, in the headline
        shipped["headline"] = [*shipped.get("headline", []), record["choice"]]
    return {"calibrated_urdf": urdf, "calibration": record, "identify": shipped}
