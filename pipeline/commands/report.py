"""``vtcal report RUN_DIR``: re-render report.html and run.rrd from a run folder's artefacts."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.commands._common import POSITIVE
from pipeline.errors import BadInput
from pipeline.io.run_folder import RUN_FILES


@click.command(
    "report",
    epilog="""\b
Examples:
  vtcal report runs/sample                 # both files, into the run folder
  vtcal report runs/sample --no-rrd        # only report.html
  vtcal report runs/sample --html /tmp/r.html --rrd /tmp/r.rrd
""",
)
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--html", "html_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Where to write the HTML report (default RUN_DIR/report.html).")  # fmt: skip
@click.option("--rrd", "rrd_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Where to write the Rerun recording (default RUN_DIR/run.rrd).")  # fmt: skip
@click.option("--no-html", is_flag=True, help="Do not write the HTML report.")
@click.option("--no-rrd", is_flag=True, help="Do not write the Rerun recording.")
@click.option("--tolerance-mm", type=POSITIVE, default=None,
              help="Judge the verdict against this tolerance (default: the one the run was "
              "given, else the recording's tolerance_mm key).")  # fmt: skip
def command(
    run_dir: Path,
    html_path: Path | None,
    rrd_path: Path | None,
    no_html: bool,
    no_rrd: bool,
    tolerance_mm: float | None,
) -> None:
    """Re-render report.html and run.rrd of RUN_DIR from its saved artefacts.

    Nothing is re-solved and the recording is not needed: images (thumbnails of
    rejected touch-ups, camera images in run.rrd) are added only if the
    recording named in RUN_DIR/recording.json is still reachable.
    """
    if not run_dir.is_dir():
        raise BadInput(f"{run_dir}: not a run folder (no such directory)")
    known = tuple(RUN_FILES[k] for k in ("recording", "touchups", "inliers", "identify"))
    if not any((run_dir / n).exists() for n in known):
        raise BadInput(f"{run_dir}: not a run folder (none of {', '.join(known)})")
    if not no_html and not no_rrd:  # both from one load of the run folder
        from pipeline.report.outputs import build_outputs

        html, rrd = build_outputs(run_dir, tolerance_mm, html_path=html_path, rrd_path=rrd_path)
        click.echo(f"report: {html} ({html.stat().st_size / 1e6:.2f} MB)")
        click.echo(f"rerun:  {rrd} ({rrd.stat().st_size / 1e6:.2f} MB)  open with: rerun {rrd}")
        return
    if not no_html:
        from pipeline.report.html import build_report

        out = build_report(run_dir, html_path, tolerance_mm)
        click.echo(f"report: {out} ({out.stat().st_size / 1e6:.2f} MB)")
    if not no_rrd:
        from pipeline.report.rrd import build_rrd

        out = build_rrd(run_dir, rrd_path)
        click.echo(f"rerun:  {out} ({out.stat().st_size / 1e6:.2f} MB)  open with: rerun {out}")
