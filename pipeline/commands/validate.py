"""``vtcal validate``: a calibration's accuracy on touch-ups it was not fitted on.

    vtcal validate CALIBRATED.urdf REC.mcap|TABLE.{csv,parquet} [--urdf NOMINAL.urdf]
        [--out DIR] [--tolerance-mm X] [--distance A:B=METRES ...] [--flange-link L]

The figures and the verdict rule are :mod:`pipeline.accuracy.validate`'s; see docs/validate.md.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from pipeline.commands._common import POSITIVE, distance_option, progress_bars
from pipeline.errors import BadInput, CalibrationFailed

if TYPE_CHECKING:
    from pipeline.kinematics.se3 import F64

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")


@dataclass
class _Input:
    """What the input gives: the touch-up table, the nominal URDF, links, metadata."""

    table: Any
    nominal_urdf: str | None
    base_link: str | None
    flange_link: str | None
    metadata: dict[str, str]
    source: str


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: cannot read the {what}: {exc}") from exc


@contextlib.contextmanager
def _run_folder(out: Path | None) -> Iterator[Path]:
    if out is not None:
        yield out
        return
    with tempfile.TemporaryDirectory(prefix="vtcal_validate_") as tmp:
        yield Path(tmp)


def _from_recording(recording: Path, folder: Path, flange_link: str | None, quiet: bool) -> _Input:
    """Ingest, touch-ups and outliers of a recording into ``folder`` (cached stages reused)."""
    import json

    from pipeline.io.artefacts import read_artefact
    from pipeline.run.catalog import OUTLIERS
    from pipeline.run.orchestrator import RunConfig, run_paths, run_pipeline

    overrides = {"flange_link": flange_link} if flange_link else {}
    with progress_bars(enabled=not quiet) as progress:
        run_pipeline(
            recording, folder, RunConfig(overrides=overrides), until=OUTLIERS, progress=progress
        )
    P = run_paths(folder)
    info = json.loads(P["recording"].read_text())
    return _Input(
        table=read_artefact(P["inliers"], "inliers"),
        nominal_urdf=info.get("urdf"),
        base_link=info.get("base_link"),
        flange_link=info.get("flange_link"),
        metadata=dict(info.get("metadata") or {}),
        source=str(recording),
    )


def _chain(urdf: Any, base: str, flange: str, path: Path) -> Any:
    from pipeline.kinematics import load_chain

    try:
        return load_chain(urdf, base, flange)
    except BadInput as exc:
        raise BadInput(f"{path}: no chain from {base!r} to {flange!r}: {exc}") from exc


@click.command(
    "validate",
    epilog="""\b
Examples:
  vtcal validate runs/sample/calibrated.urdf datasets/samples/sample_lrmate.mcap  # exit 3: refused, its own recording
  vtcal validate runs/rec1/calibrated.urdf rec2.mcap --out runs/rec2_check --tolerance-mm 0.1
  vtcal validate cal/calibrated.urdf touchups2.csv --urdf nominal.urdf --distance 0:2=0.25
""",
)
@click.argument("calibrated", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("input_path", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--urdf",
    "urdf_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Nominal URDF for the 'before' figures (default: the recording's /robot_description; "
    "required for a touch-up table).",
)
@click.option(
    "--out",
    "-o",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder for validate.json and validate.html (and, for a recording, its ingest, "
    "touchups and outliers artefacts, reused when fresh). Default: print only.",
)
@click.option(
    "--tolerance-mm",
    type=POSITIVE,
    default=None,
    help="PASS when the calibrated robot's consistency on the new touch-ups and every "
    "known-distance error are at most this and it improved on the nominal robot, else FAIL "
    "and exit 3. Default: the recording's tolerance_mm metadata key, if any.",
)
@distance_option
@click.option(
    "--base-link", default=None, help="Base link (default: the recording's, or the root)."
)
@click.option(
    "--flange-link",
    default=None,
    help="Link the pin is fixed to (default: the parent of the calibrated URDF's "
    "virtual_pin_joint).",
)
@click.option(
    "--accept-implausible",
    is_flag=True,
    help="Judge even where the touch-ups contradict the nominal robot (joint values outside "
    "the URDF's limits, a nominal fit worse than 25 mm, a known distance it contradicts); "
    "the lines are kept in validate.json as 'implausible'.",
)
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
def command(
    calibrated: Path,
    input_path: Path,
    urdf_path: Path | None,
    out: Path | None,
    tolerance_mm: float | None,
    distance: tuple[str, ...],
    base_link: str | None,
    flange_link: str | None,
    accept_implausible: bool,
    quiet: bool,
) -> None:
    """Judge CALIBRATED.urdf on INPUT, touch-ups it was NOT fitted on.

    INPUT is another recording of the same cell (MCAP) or a touch-up table
    (CSV/Parquet). Per target, the consistency of the pins the calibrated robot
    predicts, and the known-distance errors, against the nominal robot with a
    refitted pin. Exit 3 when not improved or FAIL.
    """
    from pipeline.accuracy.validate import pin_of, refusal, usable_touchups, validate
    from pipeline.accuracy.verdict import tolerance_from_metadata
    from pipeline.commands.identify import infer_links, read_table
    from pipeline.io.known_distances import parse_distances
    from pipeline.kinematics import parse_urdf

    cal_text = _read_text(calibrated, "calibrated URDF")
    try:
        cal_robot = parse_urdf(cal_text)
    except BadInput as exc:
        raise BadInput(f"{calibrated}: {exc}") from exc
    _refuse_its_own_training_data(calibrated, cal_text, input_path)
    given = [d for item in distance for d in parse_distances(item)]
    suffix = _input_suffix(input_path, urdf_path)
    pin = pin_of(cal_robot)
    flange = flange_link or (pin[0] if pin else None)
    with _run_folder(out) as folder:
        if suffix == ".mcap":
            inp = _from_recording(input_path, folder, flange_link, quiet)
        else:
            inp = _Input(read_table(input_path), None, None, None, {}, str(input_path))
        nominal_text = _read_text(urdf_path, "nominal URDF") if urdf_path else inp.nominal_urdf
        nominal_src = urdf_path or Path(f"{input_path} (/robot_description)")
        if not nominal_text:
            raise BadInput(f"{input_path}: the recording carries no robot description: give --urdf")
        try:
            base = base_link or inp.base_link or infer_links(cal_text)[0]
            flange = flange or inp.flange_link or infer_links(nominal_text)[1]
        except BadInput as exc:
            raise BadInput(f"{calibrated}: {exc}") from exc
        cal_chain = _chain(cal_robot, base, flange, calibrated)
        nom_chain = _chain(nominal_text, base, flange, nominal_src)
        if nom_chain.joint_names != cal_chain.joint_names:
            raise BadInput(
                f"{nominal_src}: joints {nom_chain.joint_names} from {base} to {flange} differ "
                f"from the calibrated URDF's {cal_chain.joint_names}: not the same robot"
            )
        cal_pin = _calibrated_pin(calibrated, pin, flange)
        data = usable_touchups(inp.table, cal_chain.joint_names, inp.source)
        kept, dropped = _known_distances(given, data.labels, inp)
        if tolerance_mm is None:
            tolerance_mm = tolerance_from_metadata(inp.metadata)
        model = _prediction_model(calibrated, cal_chain.joint_names, flange)
        result = validate(cal_chain, cal_pin, nom_chain, data, kept, tolerance_mm, model)
        if result["implausible"] and not accept_implausible:  # identify's guardrails
            raise CalibrationFailed(
                f"{inp.source}: implausible input: "
                + "; ".join(result["implausible"])
                + " (rerun with --accept-implausible if it is right)"
            )
        result.update(
            calibrated=str(calibrated),
            input=inp.source,
            nominal=str(nominal_src),
            base_link=base,
            flange_link=flange,
            notes=dropped,
        )
        _echo(result)
        if out is not None:
            _write(result, out)
    err = refusal(result)
    if err is not None:
        raise err


def _prediction_model(calibrated: Path, joints: list[str], flange: str) -> Any:
    """The run's calibration.json model beside CALIBRATED.urdf, where it is not the URDF's.

    ``elastic`` (joint compliance) predicts through its own map, which a URDF cannot
    hold; None when there is no record, it is the URDF's model, or another robot.
    """
    from pipeline.io.run_folder import RUN_FILES

    path = calibrated.parent / RUN_FILES["calibration"]
    if calibrated.name != RUN_FILES["calibrated_urdf"] or not path.is_file():
        return None
    from pipeline.use import load

    cal = load(calibrated.parent)
    same = cal.joint_names == joints and cal.record["robot"]["flange_link"] == flange
    if cal.model == cal.record.get("urdf_model") or not same:
        return None
    click.echo(f"{path.name}: predictions use {cal.model}, judged on a row of its own")
    return cal


def _input_suffix(input_path: Path, urdf_path: Path | None) -> str:
    """``.mcap`` or a table's suffix; BadInput for any other, or for a table without --urdf."""
    suffix = input_path.suffix.lower()
    if suffix not in (".mcap", *TABLE_SUFFIXES):
        raise BadInput(
            f"{input_path}: input must be a recording (.mcap) or a touch-up table (.csv, "
            f".parquet), not {suffix or 'a file without a suffix'!r}"
        )
    if suffix != ".mcap" and urdf_path is None:
        raise BadInput(
            f"{input_path}: a touch-up table needs --urdf NOMINAL.urdf for the nominal robot"
        )
    return suffix


def _calibrated_pin(calibrated: Path, pin: tuple[str, F64] | None, flange: str) -> F64 | None:
    """The calibrated URDF's pin when it is on ``flange``, else None (refitted: said why)."""
    cal_pin = pin[1] if pin and pin[0] == flange else None
    if pin is None:
        click.echo(
            f"{calibrated.name} has no virtual_pin_joint: its pin is refitted on these "
            "touch-ups (the headline then holds no pin error)"
        )
    elif cal_pin is None:
        click.echo(
            f"the virtual pin of {calibrated.name} is on {pin[0]!r}, not {flange!r}: "
            "its pin is refitted on these touch-ups"
        )
    return cal_pin


def _known_distances(
    given: list[tuple[int | str, int | str, float]], labels: list[str], inp: _Input
) -> tuple[list[tuple[str, str, float]], list[str]]:
    """(kept, dropped): the --distance ones (all must match a target), else the recording's."""
    from pipeline.accuracy.validate import match_distances
    from pipeline.io.known_distances import metadata_distances

    if given:
        kept, dropped = match_distances(given, labels, inp.source)
        if dropped:
            raise BadInput(f"--distance: {dropped[0]}")
    else:
        meta = metadata_distances(inp.metadata)
        kept, dropped = match_distances(meta, labels, inp.source)
        for line in dropped:
            click.echo(f"note: {line}")
    return kept, dropped


def _refuse_its_own_training_data(calibrated: Path, cal_text: str, input_path: Path) -> None:
    """Exit 3 when INPUT is the very file the calibration was fitted on (its provenance says).

    Judged on its own touch-ups a calibration shows a training figure, which the
    verdict would then call validated. The calibrated URDF's provenance block
    names the source's SHA-256 (16 hex); a file with the same bytes is refused.
    """
    from pipeline.errors import CalibrationFailed
    from pipeline.export.provenance import read_provenance
    from pipeline.io.fileio import file_hash

    source = read_provenance(cal_text).get("source", "")
    if not source or not input_path.is_file():
        return
    sha = file_hash(input_path)
    if source.split()[-1] == sha:
        raise CalibrationFailed(
            f"{input_path}: this is the {source.split()[0]} {calibrated.name} was fitted on "
            f"(sha256 {sha}, its provenance says): judged on its own touch-ups a calibration "
            "shows a training figure, not a validation; validate on another recording of the cell"
        )


def _echo(result: dict[str, Any]) -> None:
    """The short table and the verdict line."""
    click.echo(
        f"validate {Path(result['calibrated']).name} on {result['input']}: "
        f"{result['n_touchups']} usable touch-ups of {len(result['targets'])} targets"
        f" ({result['n_unusable']} rejected or unusable, not judged)"
    )
    heads = [f"error {r['pair']}" for r in result["robots"][0]["distances"]]
    widths = [max(14, len(h) + 2) for h in heads]
    head = f"  {'robot':<33}{'consistency':>13}{'max':>9}"
    click.echo(head + "".join(f"{h:>{w}}" for h, w in zip(heads, widths, strict=True)) + "   (mm)")
    for r in result["robots"]:
        cells = "".join(
            f"{d['error_mm']:>{w}.4f}" for d, w in zip(r["distances"], widths, strict=True)
        )
        click.echo(f"  {r['label']:<33}{r['consistency_mm']:>13.4f}{r['max_mm']:>9.4f}{cells}")
    click.echo(result["verdict"]["line"])


def _write(result: dict[str, Any], out: Path) -> None:
    from pipeline.io.fileio import atomic_write_bytes
    from pipeline.report.validate_html import render_validation
    from pipeline.run.orchestrator import write_json

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "validate.json", result)
    atomic_write_bytes(out / "validate.html", render_validation(result).encode())
    click.echo(f"wrote validate.json, validate.html to {out}")
