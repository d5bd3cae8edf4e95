"""``vtcal identify``: identify kinematics from a touch-up table (CSV or Parquet).

    vtcal identify TABLE.{parquet,csv} --urdf ROBOT.urdf --out DIR
        [--base-link L] [--flange-link L] [--distance A:B=METRES ...] [--model NAME|all]

The runner (:mod:`pipeline.run.runner`) started at identify with the table given:
identify, crossval, choose and report write into ``DIR`` what ``vtcal run``
writes from identification on (see ``docs/identification.md``).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import click
import pandas as pd

from pipeline.commands._common import (
    accept_implausible_option,
    distance_option,
    echo_verdict,
    fail_on_verdict,
    progress_bars,
    tolerance_option,
)
from pipeline.errors import BadInput
from pipeline.io.run_folder import RUN_FILES
from pipeline.io.tables import read_table
from pipeline.models import model_help


def infer_links(urdf: str) -> tuple[str, str]:
    """Root link and the end of its serial chain (a link named ``flange`` if on it)."""
    try:
        root = ET.fromstring(urdf)
    except ET.ParseError as exc:
        raise BadInput(f"URDF does not parse: {exc}") from exc
    children: dict[str, list[tuple[str, str]]] = {}
    child_links = set()
    for j in root.findall("joint"):
        p, c = j.find("parent"), j.find("child")
        if p is None or c is None:
            continue
        children.setdefault(str(p.get("link")), []).append((str(c.get("link")), str(j.get("type"))))
        child_links.add(str(c.get("link")))
    roots = [
        str(el.get("name")) for el in root.findall("link") if el.get("name") not in child_links
    ]
    if len(roots) != 1:
        raise BadInput(f"URDF has {len(roots)} root links {roots}: give --base-link")
    link, path = roots[0], [roots[0]]
    while len(children.get(link, [])) == 1:
        link = children[link][0][0]
        path.append(link)
    flange = "flange" if "flange" in path else path[-1]
    return roots[0], flange


def _table_source(table: Path, urdf_path: Path, df: pd.DataFrame, conf: dict[str, Any]) -> Any:
    """Provenance source of an identification from a table (:mod:`pipeline.export.provenance`).

    The run id hashes what decides the result: the table's and the URDF's bytes,
    the options, vtcal's version and code. The date is the table's earliest
    ``stamp_ns`` when it has that column (a run's touchups.parquet does), else unknown.
    """
    from pipeline import __version__
    from pipeline.export.provenance import Source, recorded_utc
    from pipeline.io.fileio import config_hash, file_hash
    from pipeline.run.ledger import code_digest

    sha = file_hash(table)
    request = {
        "table": sha,
        "urdf": file_hash(urdf_path),
        "options": json.loads(json.dumps(conf, default=str)),
        "version": __version__,
        "code": code_digest(),
    }
    stamps: list[Any] = (
        list(pd.to_numeric(df["stamp_ns"], errors="coerce")) if "stamp_ns" in df else []
    )
    return Source(
        kind="touch-up table",
        name=table.name,
        sha256=sha,
        run_id=config_hash(request),
        recorded_utc=recorded_utc(stamps),
    )


@click.command(
    "identify",
    epilog="""\b
Examples:
  vtcal identify datasets/real/mukca/panda_2.csv --urdf datasets/real/mukca/nominal_panda.urdf \\
      --flange-link panda_hand_tcp --distance back_left/hole_0:back_left/hole_1=0.05 --out runs/panda
  vtcal identify touchups.parquet --urdf robot.urdf --out runs/table --model all --no-report
""",
)
@click.argument("table", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--urdf",
    "urdf_path",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Nominal URDF of the robot (joint names = the table's joint columns).",
)
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder.",
)
@click.option("--base-link", default=None, help="Robot base link (default: the URDF's root link).")
@click.option(
    "--flange-link",
    default=None,
    help="Link the virtual pin is fixed to (default: 'flange' or the end of the serial chain). "
    "Name a tool link to start the pin from its fixed joint.",
)
@distance_option
@click.option(
    "--model",
    default="all",
    show_default=True,
    help=f"Error model: {model_help()}; 'all' fits each and ships the one with the smallest "
    "held-out (cross-validated) error among those a URDF can carry (elastic's URDF holds its "
    "rigid part only); 'auto' takes full if the touch-ups suffice, else offsets (and says so).",
)
@click.option("--no-crossval", is_flag=True, help="Skip cross-validation (crossval.parquet).")
@click.option("--no-report", is_flag=True, help="Skip report.html and run.rrd.")
@click.option(
    "--robust-loss",
    default="linear",
    show_default=True,
    type=click.Choice(["linear", "soft_l1", "huber", "cauchy", "arctan"]),
    help="Loss on the pin residuals (scipy least_squares).",
)
@tolerance_option
@accept_implausible_option
def command(
    table: Path,
    urdf_path: Path,
    out_dir: Path,
    base_link: str | None,
    flange_link: str | None,
    distance: tuple[str, ...],
    model: str,
    no_crossval: bool,
    no_report: bool,
    robust_loss: str,
    accept_implausible: bool,
    tolerance_mm: float | None,
) -> None:
    """Identify kinematics from a touch-up table (CSV or Parquet).

    Writes into --out what `vtcal run` writes from identification on:
    parameters.parquet, residuals.parquet, targets.parquet, calibrated.urdf (with
    virtual_pin), identify.json, crossval.parquet, report.html and run.rrd.
    """
    from pipeline.io.known_distances import parse_distances

    df = read_table(table)
    try:
        urdf = urdf_path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{urdf_path}: cannot read the URDF: {exc}") from exc
    if base_link is None or flange_link is None:
        try:
            b, f = infer_links(urdf)
        except BadInput as exc:
            raise BadInput(f"{urdf_path}: {exc}") from exc
        if base_link is None:
            base_link = b
            click.echo(f"base link: {b} (inferred: root of the URDF)")
        if flange_link is None:
            flange_link = f
            click.echo(f"flange link: {f} (inferred: end of the serial chain)")
    distances = [d for item in distance for d in parse_distances(item)]
    conf = {
        "model": model,
        "distances": distances,
        "robust_loss": robust_loss,
        "accept_implausible": accept_implausible,
    }
    from pipeline.run.catalog import CROSSVAL, IDENTIFY, REPORT
    from pipeline.run.runner import Context, build_configs, plan, run_stages

    off = ((CROSSVAL, no_crossval), (REPORT, no_report))
    names = plan(None, leave_out=tuple(n for n, leave in off if leave))
    names = names[names.index(IDENTIFY) :]
    ctx = Context(
        out_dir,
        configs=build_configs(names, {}, {IDENTIFY: conf}),
        robot=(urdf, base_link, flange_link),
        source=_table_source(table, urdf_path, df, conf),
        tolerance_mm=tolerance_mm,
        given={"inliers": df},
        force=True,  # the table is not a run-folder file: nothing to find fresh
    )
    try:
        # one bar per stage, its clock running while it works: a large table's fits and
        # cross-validation take a minute or more, never in silence
        with progress_bars() as bar:
            ctx.progress = bar
            for name in names:
                if bar is not None:
                    bar(name, 0, 1)
                run_stages([name], ctx, names)
                if bar is not None:
                    bar(name, 1, 1)
    except BadInput as exc:
        msg = str(exc)
        if msg.startswith("touch-up table"):  # name the file
            raise BadInput(f"{table}{msg[len('touch-up table') :]}") from exc
        if msg.startswith("URDF"):
            raise BadInput(f"{urdf_path}: {msg}") from exc
        raise
    written = [name for r in ctx.records for name in r.outputs]
    summary = json.loads((out_dir / RUN_FILES["identify"]).read_text())
    for line in summary.get("headline", []):
        click.echo(line)
    v = echo_verdict(summary, tolerance_mm)
    click.echo(f"wrote {', '.join(written)} to {out_dir}")
    fail_on_verdict(v)
