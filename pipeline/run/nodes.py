"""The stage functions the runner calls: data in, data out, one per row of ``catalog.STAGES``.

Each ``NAME(data, config, context)`` takes the artefacts its stage reads
(``data``: DataFrames for Parquet, dicts for JSON, text for URDFs), its options
and the run's context (:class:`pipeline.run.runner.Context`: the recording, the
robot, the provenance source), calls the stage's computation in
``pipeline/stages/`` and returns ``{artefact key: value}`` for the runner to
write. Nothing here writes a file, except the report (its two files are
written by the HTML and Rerun writers themselves).

The computations are looked up on their modules at call time, so a function
replaced at run time is the one that runs (and the one the stage code key
hashes, :mod:`pipeline.run.code_key`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

from pipeline.io.run_folder import Parquet


def _info(recording: dict[str, Any]) -> Any:
    """``recording.json`` as the :class:`~pipeline.stages.ingest.stage.RecordingInfo` stages take."""
    from pipeline.stages.ingest.stage import RecordingInfo

    return RecordingInfo(**recording)


def ingest(data: dict[str, Any], config: dict[str, Any], context: Any) -> dict[str, Any]:
    """frames, detections and recording.json from the recording (one streaming pass)."""
    from pipeline.stages.detect.precompile import compile_detector
    from pipeline.stages.ingest import stage

    progress = context.progress

    def cb(done: int, total: int | None) -> None:
        if progress:
            progress("ingest", done, total)

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
        context.recording.resolve(), config["ingest"], config["detect"], progress=cb
    )
    joint_meta = {"joint_names": json.dumps(list(info.joint_names))}
    return {
        "frames": Parquet(frames, joint_meta),
        "detections": Parquet(detections),
        "recording": info,
    }


def touchups(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """touchups.parquet from frames and detections (its implied target size and the designated
    values used in the metadata)."""
    from pipeline.stages.touchups import stage as touchup

    info = _info(data["recording"])
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


def outliers(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """inliers.parquet: every touch-up, flagged (with the reason of each rejection)."""
    from pipeline.stages.outliers import stage as stage

    return {"inliers": stage.flag_outliers(data["touchups"], _info(data["recording"]), config)}


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
        tu = _meta(data, "touchups")
        implied = _finite(tu.get("implied_target_diameter_m"))
        # the pose component's unseen mean: a pin offset in the predicted errors (P1)
        pose = pin_offset_cov(json.loads(tu.get("capture_noise") or "{}"))
        config = dataclasses.replace(
            config, implied_target_diameter_m=implied, pin_offset_cov_m2=pose
        )
    results = stage.identify(data["inliers"], urdf, base_link, flange_link, config)
    return stage.fit_outputs(results)


def _meta(data: Any, key: str) -> dict[str, str]:
    """The ``vtcal.*`` metadata of Parquet input ``key``; from the runner's inputs without
    reading the table's rows (:meth:`pipeline.run.runner.Inputs.meta`)."""
    meta = getattr(data, "meta", None)
    return dict(meta(key)) if meta is not None else dict(data[key].attrs["vtcal"])


def _finite(text: str | None) -> float | None:
    """A metadata number, None when absent, not a number or not finite."""
    try:
        value = float(text) if text else float("nan")
    except ValueError:
        return None
    return value if math.isfinite(value) else None


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


def crossval(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """crossval.parquet: held-out residuals per model; its summary rides in the metadata."""
    from pipeline.stages.crossval import stage

    urdf, base_link, flange_link = context.robot
    table, id_config = integer_target_ids(data["inliers"], context.configs["identify"])
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


def choose(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """calibrated.urdf, calibration.json and identify.json: the shipped models.

    :mod:`pipeline.stages.choose.stage` picks the URDF's model,
    :mod:`pipeline.use.record` records the model predictions use.
    """
    from pipeline.stages.choose import stage
    from pipeline.stages.outliers.adequacy import trust
    from pipeline.use.record import calibration_record

    # the cross-validation summary and the capture noise ride in their tables' metadata
    summary = json.loads(_meta(data, "crossval")["summary"]) if "crossval" in data else None
    urdf, shipped = stage.choose_model(data["models"], data["model_urdfs"], summary, context.source)
    tu = _meta(data, "touchups") if "touchups" in data else None
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


def report(data: dict[str, Any], config: Any, context: Any) -> dict[str, Any]:
    """report.html and run.rrd from the run folder's artefacts alone (written by their writers)."""
    warm = getattr(context, "warm_report", None)
    built = warm.build(context.out, context.tolerance_mm) if warm is not None else None
    if built is None:  # no warm process (pipeline.report.warm), or it is gone
        from pipeline.report import outputs

        built = outputs.build_outputs(context.out, context.tolerance_mm)
    html, rrd = built
    return {"report": html, "rrd": rrd}
