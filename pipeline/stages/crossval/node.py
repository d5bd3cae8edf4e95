"""The crossval stage's node: inliers and identify's fits in, crossval.parquet out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from pipeline.io.run_folder import Parquet


def integer_target_ids(table: Any, config: Any) -> tuple[Any, Any]:
    """Table and identify config with target labels as integers 0, 1, ... in first-appearance order.

    The spec lets ``target_id`` be a string; cross-validation's artefact keys
    targets by integer, so string labels (and the known distances naming them)
    are numbered in the order the table first names them. Integer labels are
    returned as they are.
    """
    import pandas as pd

    if pd.api.types.is_integer_dtype(table["target_id"]):
        return table, config
    labels = list(dict.fromkeys(table["target_id"].astype(str)))
    code = {lab: i for i, lab in enumerate(labels)}
    out = table.copy()
    out["target_id"] = table["target_id"].astype(str).map(code).astype("int64")
    distances = [
        (code.get(str(a), a), code.get(str(b), b), metres) for a, b, metres in config.distances
    ]
    return out, dataclasses.replace(config, distances=distances)


def crossval(data: dict[str, Any], config: Any, context: Any, *, identify: Any) -> dict[str, Any]:
    """crossval.parquet: held-out residuals per model; its summary rides in the metadata.

    ``identify``: identify's options, which the refits fit with (the catalog declares
    them, ``Stage.uses_configs``, and the runner hands them over)."""
    from pipeline.stages.crossval import stage

    urdf, base_link, flange_link = context.robot
    table, id_config = integer_target_ids(data["inliers"], identify)
    models = data["models"].get("models")
    result = stage.cross_validate(
        table,
        urdf,
        base_link,
        flange_link,
        id_config,
        config,
        full_fits=models if isinstance(models, dict) else None,
    )
    summary = json.dumps(result.summary, sort_keys=True, allow_nan=False)
    return {"crossval": Parquet(result.table, {"summary": summary})}
