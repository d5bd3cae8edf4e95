"""``vtcal run``: one recording through every stage, into one run folder."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from pipeline.accuracy.verdict import tolerance_from_metadata
from pipeline.commands._common import (
    accept_implausible_option,
    distance_option,
    echo_summary,
    fail_on_verdict,
    progress_bars,
    set_option,
    split_stage_options,
    tolerance_option,
)
from pipeline.io.run_folder import RUN_FILES
from pipeline.run.catalog import IDENTIFY, INGEST
from pipeline.run.orchestrator import STAGES, RunConfig, run_pipeline


@click.command(
    "run",
    epilog="""\b
Examples:
  vtcal run datasets/samples/sample_lrmate.mcap --out runs/sample
  vtcal run rec.mcap --out runs/rec --until touchups      # stop after extraction
  vtcal run rec.mcap --out runs/rec --model all           # fit every error model
  vtcal run rec.mcap --out runs/rec --set polarity=light_on_dark --distance 0:2=0.25
  vtcal run my_bag/ --out runs/bag --joint-prefix robot1/   # ros2 bag record directory
  vtcal run cell.bag --out runs/cell --set target_diameter_m=0.02   # ROS 1 bag
""",
)
@click.argument("recording", type=click.Path(path_type=Path))
@click.option(
    "--out",
    "-o",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Run folder to write the artefacts into (created).",
)
@click.option("--until", type=click.Choice(STAGES), default=None, help="Stop after this stage.")
@click.option("--force", is_flag=True, help="Re-run every stage even if its outputs are fresh.")
@click.option(
    "--model",
    default=None,
    help="Error model to identify (see `vtcal identify --help`); default: all, the run ships the one with the smallest held-out error.",
)
@distance_option
@set_option
@click.option("--image-topic", default=None, help="Image topic (default: auto-detect).")
@click.option("--joint-topic", default="/joint_states", show_default=True)
@click.option("--description-topic", default="/robot_description", show_default=True)
@click.option(
    "--joint-prefix",
    default="",
    metavar="PREFIX",
    help="Strip PREFIX from joint-state names before matching them with the URDF's "
    "(robot1/ makes robot1/joint_1 joint_1).",
)
@click.option("--base-link", default=None, help="URDF base link (overrides the metadata).")
@click.option("--flange-link", default=None, help="URDF flange link (overrides the metadata).")
@click.option("--no-report", is_flag=True, help="Skip report.html and run.rrd.")
@accept_implausible_option
@tolerance_option
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
def command(
    recording: Path,
    out: Path,
    until: str | None,
    force: bool,
    model: str | None,
    distance: tuple[str, ...],
    overrides: dict[str, str],
    image_topic: str | None,
    joint_topic: str,
    description_topic: str,
    joint_prefix: str,
    base_link: str | None,
    flange_link: str | None,
    no_report: bool,
    accept_implausible: bool,
    tolerance_mm: float | None,
    quiet: bool,
) -> None:
    """Calibrate from RECORDING: an MCAP file per spec/recording.md, or a ROS bag
    (rosbag2 directory of .mcap or .db3 files, a .db3 file, a ROS 1 .bag; docs/ros-bags.md).

    Writes into --out one Parquet artefact per stage (frames, detections,
    touchups, inliers, parameters, residuals, targets, crossval), calibrated.urdf
    with the virtual pin, report.html and run.rrd. Stages whose inputs and
    options are unchanged are skipped.
    """
    overrides = dict(overrides)
    if base_link:
        overrides["base_link"] = base_link
    if flange_link:
        overrides["flange_link"] = flange_link
    if distance:
        overrides["known_distances"] = ";".join(distance)
    overrides, stage_options = split_stage_options(overrides)
    if model:
        stage_options.setdefault(IDENTIFY, {})["model"] = model
    if joint_prefix:
        stage_options.setdefault(INGEST, {})["joint_prefix"] = joint_prefix
    if accept_implausible:
        stage_options.setdefault(IDENTIFY, {})["accept_implausible"] = True
    cfg = RunConfig(
        image_topic=image_topic,
        joint_topic=joint_topic,
        description_topic=description_topic,
        overrides=overrides,
        stage_options=stage_options,
        report=not no_report,
        tolerance_mm=tolerance_mm,
    )
    # a refusal leaves nothing in --out and carries ingest's warnings in its one line
    # (pipeline.run.orchestrator.run_pipeline)
    with progress_bars(enabled=not quiet) as progress:
        result = run_pipeline(recording, out, cfg, until=until, force=force, progress=progress)
    rec = _recording_json(out)
    if tolerance_mm is None:
        tolerance_mm = tolerance_from_metadata(rec.get("metadata"))
    v = echo_summary(result, tolerance_mm)
    for line in rec.get("warnings") or []:  # ingest's (truncation, skipped chunks, ...)
        click.echo(f"vtcal: warning: {line}", err=True)
    fail_on_verdict(v)


def _recording_json(out: Path) -> dict[str, Any]:
    """``recording.json`` of the run folder ({} when absent or unreadable)."""
    import json

    try:
        data = json.loads((out / RUN_FILES["recording"]).read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
