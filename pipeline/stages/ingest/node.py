"""The ingest stage's node: the recording in, frames, detections and recording.json out.

The contract every node keeps is :mod:`pipeline.stages`' (its last paragraph).
"""

from __future__ import annotations

import json
from typing import Any

from pipeline.io.run_folder import Parquet


def ingest(data: dict[str, Any], config: dict[str, Any], context: Any) -> dict[str, Any]:
    """frames, detections and recording.json from the recording (one streaming pass)."""
    from pipeline.stages.detect.precompile import compile_detector
    from pipeline.stages.ingest import stage

    progress, name = context.progress, context.stage  # name: the catalog's, its options' group

    def cb(done: int, total: int | None) -> None:
        if progress:
            progress(name, done, total)

    # a fresh install compiles the detector first (~10-20 s): never a silent wait
    slow: list[bool] = []

    def announce() -> None:
        slow.append(True)
        if progress:
            progress("compile", 0, None)

    compile_detector(config["detect"], on_slow=announce)
    if slow and progress:
        progress("compile", 1, 1)
    frames, detections, info = stage.ingest_recording(
        context.recording.resolve(), config[name], config["detect"], progress=cb
    )
    joint_meta = {"joint_names": json.dumps(list(info.joint_names))}
    return {
        "frames": Parquet(frames, joint_meta),
        "detections": Parquet(detections),
        "recording": info,
    }
