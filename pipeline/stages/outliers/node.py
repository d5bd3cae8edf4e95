"""The outliers stage's node: touchups in, inliers.parquet (every touch-up, flagged) out.

Called by the runner as declared in :data:`pipeline.run.catalog.STAGES`: the
artefacts the stage reads (``data``), its options and the run's context
(:class:`pipeline.run.runner.Context`) in, ``{artefact key: value}`` out for the
runner to write; nothing here writes a file. The stage's computation is
imported inside the function, so importing this module stays cheap (the catalog
imports it) and a function replaced at run time is the one that runs (and the one
the stage code key hashes, :mod:`pipeline.run.code_key`).
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
