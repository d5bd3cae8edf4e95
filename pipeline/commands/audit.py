"""``vtcal audit RUN_DIR ...``: robots over time: drift, changes and their cause, models ranked."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from pipeline.commands._common import POSITIVE


@click.command(
    "audit",
    epilog="""\b
Examples:
  vtcal audit runs/sample --robot-id sample --out audit/   # one run: its models ranked
  vtcal batch --manifest fleet.toml --out fleet_runs/ --until outliers  # Dask if asked
  vtcal audit fleet_runs/ --out audit/              # every run folder under fleet_runs/
  vtcal audit fleet_runs/cell3-* --tolerance-mm 0.05 --fail-on-change
""",
)
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("audit"), show_default=True,
              help="Folder for audit_{recordings,changes,models}.parquet, audit.html, audit.rrd.")  # fmt: skip
@click.option("--tolerance-mm", type=POSITIVE, default=0.1, show_default=True,
              help="PASS when the previous calibration's drift and consistency are within it.")  # fmt: skip
@click.option("--alpha", type=float, default=0.001, show_default=True,
              help="Level of the change test per comparison (measured false alarms: about "
              "2-4x it on fresh simulated histories, 0.3 % at the default; docs/audit.md).")  # fmt: skip
@click.option("--manifest", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The batch manifest: its entries' robot_id name the runs' robots.")  # fmt: skip
@click.option("--robot-id", default=None,
              help="Robot identity for recordings without the robot_id metadata key.")  # fmt: skip
@click.option("--models", default="offsets,mdh,full,poe", show_default=True,
              help="Error models ranked across the fleet (comma-separated).")  # fmt: skip
@click.option("--executor", type=click.Choice(("processes", "dask")), default="processes",
              show_default=True,
              help="Where the fits run: a local process pool, or Dask (as `vtcal batch`).")  # fmt: skip
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Dask scheduler (tcp://host:8786) whose workers see the run folders; "
              "without it Dask starts a local cluster.")  # fmt: skip
@click.option("--workers", "-j", type=int, default=None,
              help="Worker processes (default: the free cores; 1: in this process).")  # fmt: skip
@click.option("--interval-days", type=POSITIVE, default=None,
              help="The fleet page calls a robot overdue when its last recording is older than "
              "this many days (counted to the audit's time). Default: none is.")  # fmt: skip
@click.option("--fail-on-change", is_flag=True,
              help="Exit with status 5 when a robot changed (the audit's files are written).")  # fmt: skip
def command(
    run_dirs: tuple[Path, ...], out: Path, tolerance_mm: float, alpha: float,
    manifest: Path | None, robot_id: str | None, models: str, executor: str,
    scheduler: str | None, workers: int | None,
    fail_on_change: bool, interval_days: float | None,
) -> None:  # fmt: skip
    """Audit robots over time from run folders (`vtcal run` / `vtcal batch`).

    Runs with the same robot_id (the recording's, its --manifest entry's, or
    --robot-id) form a history, ordered by their first stamp.
    Per recording: the previous calibration validated on it and its drift;
    between consecutive recordings: a chi-square change test with a stated
    false-alarm rate and the one physical cause that explains a change (joint
    zero, link, camera/pin, base, or different robots); across the fleet: the
    error models ranked by held-out error. Writes Parquet tables and HTML pages:
    audit.html, every robot in the order of attention, and robots/ROBOT.html.
    """
    from pipeline.audit.engine import prestart
    from pipeline.batch.executor import check_executor_options

    check_executor_options(executor, workers or None, scheduler)  # 0: the free cores
    prestart(executor, workers)
    from pipeline.audit.audit import run_audit
    from pipeline.audit.identity import load_item, manifest_ids, run_folders
    from pipeline.audit.page import write_pages
    from pipeline.audit.rrd import write_rrd
    from pipeline.audit.work import work_line
    from pipeline.errors import BadInput
    from pipeline.io.artefacts import write_artefact

    if not 0 < alpha < 1:
        raise BadInput(f"--alpha {alpha}: must be between 0 and 1")
    names = tuple(m.strip() for m in models.split(",") if m.strip())
    ids = manifest_ids(manifest) if manifest is not None else {}
    items = [load_item(f, robot_id, ids, table=False) for f in run_folders(list(run_dirs))]
    res = run_audit(items, tolerance_mm=tolerance_mm, alpha=alpha, models=names, workers=workers,
                    executor=executor, scheduler=scheduler, cache_dir=out)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    cfg = {"tolerance_mm": tolerance_mm, "alpha": alpha, "models": list(names)}
    for name, table in (
        ("audit_recordings", res.recordings), ("audit_changes", res.changes),
        ("audit_models", res.models),
    ):  # fmt: skip
        write_artefact(out / f"{name}.parquet", table, name, stage="audit", config=cfg)
    page = write_pages(res, out, interval_days=interval_days)
    write_rrd(res, out / "audit.rrd")
    for line in res.lines:
        click.echo(line)
    click.echo(work_line(res.counts))
    click.echo(f"tables: {out}/audit_*.parquet   page: {page}   Rerun: {out}/audit.rrd")
    if fail_on_change and bool(res.changes["changed"].any()):
        from pipeline.errors import EXIT_CHANGED

        n = int(res.changes["changed"].sum())
        click.echo(f"vtcal audit: {n} change(s) found; exit {EXIT_CHANGED} (--fail-on-change)",
                   err=True)  # fmt: skip
        sys.exit(EXIT_CHANGED)
