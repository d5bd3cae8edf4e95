"""The touchups stage's node: frames and detections in, touchups.parquet out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

import json
from typing import Any

from pipeline.io.run_folder import Parquet


def touchups(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """touchups.parquet from frames and detections (its implied target size and the designated
    values used in the metadata)."""
    from pipeline.stages.ingest.types import RecordingInfo
    from pipeline.stages.touchups import stage as touchup

    info = RecordingInfo(**data["recording"])
    table = touchup.extract_touchups(data["frames"], data["detections"], info, config)
    implied = table.attrs.get("implied_target_diameter_m", float("nan"))
    meta = {"implied_target_diameter_m": repr(float(implied))}
    # the designated values used, and how those the recording lacked were found
    how = {k: v for k, v in info.inferred.items() if k.startswith(("designated", "threshold"))}
    meta["designated"] = json.dumps({**table.attrs.get("designated", {}), "inferred": how})
    meta["settle"] = json.dumps(table.attrs.get("settle") or {})  # the report shows it
    # the repeated captures' scatter: the detection noise the fit is tested against
    meta["capture_noise"] = json.dumps(table.attrs.get("capture_noise") or {})
    return {"touchups": Parquet(table, meta)}
