"""``vtcal batch``: many recordings through the pipeline, cached, in parallel (docs/batch.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from pipeline.batch.run import EXECUTORS, BatchIncomplete, BatchResult, RecordingOutcome
from pipeline.commands._common import (
    accept_implausible_option,
    distance_option,
    set_option,
    split_stage_options,
)
from pipeline.errors import BadInput


def _not_a_manifest(
    ctx: click.Context, param: click.Parameter, value: tuple[Path, ...]
) -> tuple[Path, ...]:
    """Refuse a manifest given as a recording (it would be read as one, and fail late)."""
    for p in value:
        if p.suffix.lower() == ".toml":
            raise click.UsageError(
                f"{p} looks like a manifest (TOML), not a recording: use --manifest {p}", ctx
            )
    return value


@click.command(
    "batch",
    epilog="""\b
Examples:
  vtcal batch runs_in/*.mcap --out runs/fleet
  vtcal batch --manifest datasets/fleet_demo.toml --out runs/fleet_demo --workers 2
  vtcal batch --manifest datasets/fleet_demo.toml --out runs/fleet_demo --until identify
  vtcal batch --manifest datasets/fleet_demo.toml --out runs/fleet_demo --executor dask
  vtcal batch --manifest fleet.toml --out /shared/runs --executor dask --scheduler tcp://head:8786
""",
)
@click.argument("recordings", nargs=-1, type=click.Path(path_type=Path), callback=_not_a_manifest)
@click.option(
    "--manifest",
    "-m",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Dataset manifest (TOML, datasets/NAME.toml) listing the recordings.",
)
@click.option(
    "--out",
    "-o",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Batch folder: one run folder per recording, and summary.parquet.",
)
@click.option(
    "--executor",
    type=click.Choice(EXECUTORS),
    default="processes",
    show_default=True,
    help="Local process pool, or Dask distributed (pip install 'vtcal[dask]').",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDRESS",
    help="Dask scheduler (tcp://host:8786) of a cluster started apart; its workers must run "
    "the same vtcal and see --out at the same path (checked first). Without it Dask starts "
    "a local cluster.",
)
@click.option(
    "--workers",
    "-j",
    type=int,
    default=None,
    help="Worker processes (default: the usable cores; ignored with --scheduler).",
)
@click.option(
    "--until",
    default=None,
    metavar="STAGE",
    help="Stop after this stage (ingest, touchups, outliers, identify, crossval, report).",
)
@click.option(
    "--recycle",
    type=int,
    default=10,
    show_default=True,
    metavar="N",
    help="Process pool: replace each worker process after N recordings (bounds its memory; "
    "0 = never).",
)
@click.option("--force", is_flag=True, help="Re-run every stage even if its outputs are fresh.")
@click.option("--model", default=None, help="Error model to identify, or 'all' (as `vtcal run`).")
@distance_option
@set_option
@click.option("--no-report", is_flag=True, help="Skip report.html and run.rrd.")
@accept_implausible_option
@click.option("--quiet", "-q", is_flag=True, help="No progress bar, no per-recording lines.")
def command(
    recordings: tuple[Path, ...],
    manifest: Path | None,
    out: Path,
    executor: str,
    scheduler: str | None,
    workers: int | None,
    until: str | None,
    recycle: int,
    force: bool,
    model: str | None,
    distance: tuple[str, ...],
    overrides: dict[str, str],
    no_report: bool,
    accept_implausible: bool,
    quiet: bool,
) -> None:
    """Run every recording (RECORDINGS, or those of --manifest) through the pipeline.

    Each recording gets its own run folder OUT/<name>/ (name: the file stem, or the
    manifest's name), exactly as `vtcal run` would write it. Stages whose inputs,
    options and code version are unchanged are skipped, so running a batch again
    only redoes what changed, and an interrupted batch resumes where it stopped.
    A recording that fails is reported with its error and does not stop the
    others. At the end OUT/summary.parquet holds one row per recording, a table
    is printed, and the identified runs are compared (OUT/compare.parquet and
    compare.html, as `vtcal compare`). Exit status 0 when every recording
    finished, 1 otherwise. See docs/batch.md.
    """
    from pipeline.batch.run import default_workers, items_from_paths, load_manifest, run_batch

    if manifest is not None and recordings:
        raise BadInput("give recordings or --manifest, not both")
    if manifest is None and not recordings:
        raise BadInput("no recordings: give RECORDINGS... or --manifest datasets/NAME.toml")
    if workers is not None and workers < 1:
        raise BadInput(f"--workers {workers}: needs at least 1")
    items = load_manifest(manifest).items if manifest else tuple(items_from_paths(recordings))

    # light: no numeric library. The workers' fork server is started by run_batch,
    # only when some recording is not already complete (the run ledger says which).
    from pipeline.run.catalog import IDENTIFY
    from pipeline.run.orchestrator import STAGES, RunConfig

    if until is not None and until not in STAGES:
        raise BadInput(f"--until {until!r}: not a stage (stages: {', '.join(STAGES)})")

    overrides = dict(overrides)
    if distance:
        overrides["known_distances"] = ";".join(distance)
    overrides, stage_options = split_stage_options(overrides)
    if model:
        stage_options.setdefault(IDENTIFY, {})["model"] = model
    if accept_implausible:
        stage_options.setdefault(IDENTIFY, {})["accept_implausible"] = True
    cfg = RunConfig(overrides=overrides, stage_options=stage_options, report=not no_report)

    console = summary_console()
    where = f"scheduler {scheduler}" if scheduler else f"{workers or default_workers()} worker(s)"
    if not quiet:
        console.print(f"batch: {len(items)} recording(s) -> {out} ({executor}, {where})")
    try:
        if quiet:
            result = run_batch(
                items,
                out,
                cfg,
                kind=executor,
                workers=workers,
                scheduler=scheduler,
                until=until,
                force=force,
                recycle_after=recycle,
            )
        else:
            result = _run_with_progress(
                console, items, out, cfg, executor, workers, scheduler, until, force, recycle
            )
    except KeyboardInterrupt:
        click.echo(
            f"vtcal batch: interrupted; what finished is in {out / 'summary.parquet'} and "
            "cached: run the same command again to resume",
            err=True,
        )
        raise
    print_summary(console, result)
    if result.failed:
        raise BatchIncomplete(
            f"{len(result.failed)} of {len(result.outcomes)} recording(s) failed "
            f"(see {result.summary_path})"
        )
    failing = [o.name for o in result.outcomes if o.verdict == "FAIL"]
    if failing:  # as `vtcal run` of each would: exit 3
        from pipeline.errors import CalibrationFailed

        raise CalibrationFailed(
            f"verdict FAIL for {len(failing)} of {len(result.outcomes)} recording(s) "
            f"({', '.join(failing)}): their validated error misses the recording's "
            f"tolerance_mm or did not improve (see {result.summary_path})"
        )


def _run_with_progress(
    console: Any,
    items: Any,
    out: Path,
    cfg: Any,
    executor: str,
    workers: int | None,
    scheduler: str | None,
    until: str | None,
    force: bool,
    recycle: int,
) -> BatchResult:
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from pipeline.batch.run import run_batch

    with Progress(
        TextColumn("[bold]recordings"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as bars:
        task = bars.add_task("recordings", total=len(items))

        def update(done: int, total: int, rec: RecordingOutcome) -> None:
            bars.update(task, completed=done, total=total)
            bars.console.print(_line(rec), highlight=False, markup=False)

        return run_batch(
            items,
            out,
            cfg,
            kind=executor,
            workers=workers,
            scheduler=scheduler,
            until=until,
            force=force,
            progress=update,
            recycle_after=recycle,
        )


def _line(rec: RecordingOutcome) -> str:
    """One line per finished recording: its state and verdict as ``vtcal run`` would say it."""
    if rec.status != "ok":
        return f"  FAIL {rec.name}: {rec.error}"
    ran = sum(st == "ran" for _, st, _ in rec.stages)
    cached = sum(st == "cached" for _, st, _ in rec.stages)
    text = f"  {rec.state:<4} {rec.name}: {ran} ran, {cached} cached, {rec.seconds:.1f} s"
    line = rec.figures.get("verdict_line")
    return f"{text}; {line}" if line else text


def _fmt(v: Any, spec: str) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    return format(v, spec)


#: width of the batch table when stdout is not a terminal (a file, a pipe, CI logs): wide
#: enough that no column is clipped or wrapped (rich would take 80)
OFF_TERMINAL_WIDTH = 400


def summary_console(file: Any = None) -> Any:
    """The console the batch prints to: the terminal's width, or unclipped off a terminal."""
    import sys

    from rich.console import Console

    stream = file if file is not None else sys.stdout
    tty = bool(getattr(stream, "isatty", lambda: False)())
    return Console(file=file, width=None if tty else OFF_TERMINAL_WIDTH)


def print_summary(console: Any, result: BatchResult) -> None:
    """The batch table: one row per recording, then the cross-run comparison if available."""
    from rich.table import Table

    table = Table(title=f"batch {result.out_dir}", title_justify="left")
    table.add_column("recording", no_wrap=True)
    cols = ("status", "ran/cached", "s", "MB", "model", "used", "validated mm", "how", "nominal mm")
    for col in (*cols, "training mm"):
        table.add_column(col, justify="left" if col in ("status", "model", "how") else "right")
    for o in result.outcomes:
        f = o.figures
        ran = sum(st == "ran" for _, st, _ in o.stages)
        cached = sum(st == "cached" for _, st, _ in o.stages)
        how = str(f.get("validated_how") or "")
        table.add_row(
            o.name,
            o.state,
            f"{ran}/{cached}" if o.status == "ok" else "-",
            _fmt(o.seconds, ".1f"),
            _fmt(o.peak_rss_mb, ".0f"),
            f.get("model") or "-",
            _fmt(f.get("n_used"), "d"),
            _fmt(f.get("validated_mm"), ".4f"),
            "held-out" if how.startswith("held-out") else ("predicted" if how else "-"),
            _fmt(f.get("nominal_mm"), ".4f"),
            _fmt(f.get("rms_mm"), ".4f"),
        )
    console.print(table)
    for o in result.failed:
        console.print(f"{o.name}: {o.error_kind}: {o.error}", highlight=False, markup=False)
    for o in result.outcomes:
        if o.retried:
            console.print(
                f"{o.name}: its worker died; it was run once more in a fresh worker",
                highlight=False,
                markup=False,
            )
    for line in result.compare_lines:  # kept in batch.json: no pandas when nothing changed
        console.print(line, highlight=False, markup=False)
    console.print(f"comparison: {result.compare_note}", highlight=False, markup=False)
    states = [o.state for o in result.outcomes]
    judged = "".join(
        f", {states.count(w)} {w}" for w in ("not improved", "FAIL") if states.count(w)
    )
    failed = f", {len(result.failed)} did not finish" if result.failed else ""
    console.print(
        f"{states.count('ok')} of {len(result.outcomes)} recording(s) ok{judged}{failed} in "
        f"{result.seconds:.1f} s; summary: {result.summary_path}",
        highlight=False,
    )
    console.print(
        "validated mm: the shipped model's held-out (k-fold) RMS, or covariance-predicted "
        "('how'); 'ok' means improved on the nominal robot (and within tolerance); training mm "
        "is the fit residual, not an accuracy",
        highlight=False,
        markup=False,
    )
