"""``vtcal export RUN_DIR --format F [--out FILE]``: the calibration in a format robot software loads.

Formats (``docs/export.md``): ``urdf``, ``ur-calibration``, ``offsets``, ``dh``,
``json``; the maths lives in :mod:`pipeline.export`, one module per format.
Without ``--out`` the file goes to stdout; with it, it is written atomically
(all or nothing) and one line on stderr says where. A format the robot does not
allow (e.g. ``ur-calibration`` for a 7-joint arm) is refused with one line,
exit 3, nothing written.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from pipeline.export import FORMATS


@click.command(
    "export",
    epilog="""\b
Examples:
  vtcal export runs/sample --format offsets         # the shipped sample's run (vtcal run --help)
  vtcal export runs/cell1 --format urdf --out cell1_calibrated.urdf
  vtcal export runs/ur5e --format ur-calibration --out my_robot_calibration.yaml
  vtcal export runs/cell1 --format offsets --joint-signs 1,1,-1,1,1,1
  vtcal export runs/cell1 --format dh
  vtcal export runs/cell1 --format json --out cell1.json
""",
)
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--format", "fmt", required=True, type=click.Choice(list(FORMATS)),
              help="What to write (see docs/export.md).")  # fmt: skip
@click.option("--out", "out_path", default=None, type=click.Path(dir_okay=False, path_type=Path),
              help="File to write (default: stdout).")  # fmt: skip
@click.option("--joint-signs", default=None, metavar="S1,S2,...",
              help="offsets/json: +1 or -1 per joint, -1 where the controller counts the joint "
              "opposite to the URDF axis (default: all +1).")  # fmt: skip
def command(run_dir: Path, fmt: str, out_path: Path | None, joint_signs: str | None) -> None:
    """Write RUN_DIR's shipped calibration in format F (urdf, ur-calibration, offsets, dh, json)."""
    from pipeline.errors import ExportRefused

    try:
        text = _render(run_dir, fmt, joint_signs)
    except ExportRefused as exc:
        raise ExportRefused(f"{run_dir}: {exc}") from exc
    if out_path is None or str(out_path) == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    from pipeline.io.fileio import atomic_write_bytes

    atomic_write_bytes(out_path, text.encode())
    click.echo(f"wrote {fmt} of {run_dir} to {out_path}", err=True)


def _render(run_dir: Path, fmt: str, joint_signs: str | None) -> str:
    """The text of format ``fmt`` for the run in ``run_dir``."""
    from pipeline.export.calibration import load_run
    from pipeline.export.offsets import parse_signs

    cal = load_run(run_dir)
    signs = parse_signs(joint_signs, cal.chain.n_dof)
    if fmt == "urdf":
        from pipeline.export.urdf import urdf_text

        text = urdf_text(cal)
    elif fmt == "ur-calibration":
        from pipeline.export.ur import ur_yaml

        text = ur_yaml(cal)
    elif fmt == "offsets":
        from pipeline.export.offsets import offsets_data, offsets_text

        text = offsets_text(cal, signs)
        c = offsets_data(cal, signs)["cost"]

        def mm(v: float | None) -> str:
            return f"{v:.4f} mm" if v is not None else "n/a"

        click.echo(
            "offsets: link-geometry corrections dropped; held-out RMS "
            f"{mm(c['offsets_heldout_rms_mm'])} with offsets only vs "
            f"{mm(c['shipped_heldout_rms_mm'])} with the shipped model {c['shipped_model']} "
            f"(fit {mm(c['offsets_fit_rms_mm'])} vs {mm(c['shipped_fit_rms_mm'])})",
            err=True,
        )
    elif fmt == "dh":
        from pipeline.export.dh import dh_text

        text = dh_text(cal)
    else:
        from pipeline.export.machine import export_json

        text = export_json(cal, signs)
    return text
