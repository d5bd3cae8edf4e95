"""The outliers stage's node: touchups in, inliers.parquet (every touch-up, flagged) out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

from typing import Any


def outliers(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """inliers.parquet: every touch-up, flagged (with the reason of each rejection)."""
    from pipeline.stages.ingest.types import RecordingInfo
    from pipeline.stages.outliers import stage

    return {
        "inliers": stage.flag_outliers(data["touchups"], RecordingInfo(**data["recording"]), config)
    }
