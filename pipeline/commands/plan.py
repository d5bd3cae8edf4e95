"""``vtcal plan``: choose well-conditioned measuring poses (docs/planner.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from pipeline.errors import BadInput
from pipeline.models import model_names


def _parse_xyz(ctx: click.Context, param: click.Parameter, value: str) -> tuple[float, ...]:
    try:
        v = tuple(float(s) for s in value.split(","))
    except ValueError:
        raise click.BadParameter(f"{value!r}: expected X,Y,Z in metres") from None
    if len(v) != 3:
        raise click.BadParameter(f"{value!r}: expected three numbers X,Y,Z")
    return v


def _summary_lines(s: dict[str, Any], out: Path) -> list[str]:
    b, a = s["indices_before"], s["indices_after"]
    pb, pa = s["predicted_before"], s["predicted_after"]
    c = s["candidates"]
    rej = ", ".join(f"{k} {v}" for k, v in c["rejected"].items() if v) or "none"
    per = ", ".join(f"{k}: {v}" for k, v in s["poses_per_target"].items())
    return [
        f"{out}: {s['n_poses']} poses on {s['n_targets']} targets ({per}); "
        f"criterion {s['criterion']}, model {s['model']} "
        f"({s['n_identifiable']}/{s['n_params']} parameter directions identifiable)",
        f"candidates: {c['usable']}/{c['total']} usable (rejected: {rej})",
        f"observability (random {s['n_poses']} -> planned): "
        f"O1 {b['O1']:.4g} -> {a['O1']:.4g}, O3 {b['O3']:.4g} -> {a['O3']:.4g}, "
        f"O4 {b['O4']:.4g} -> {a['O4']:.4g}, cond {b['cond']:.4g} -> {a['cond']:.4g}",
        f"predicted pin error after calibration (sigma {s['sigma_pin_mm']:.4f} mm per axis), "
        f"shape RMS: {pb['shape_rms_mm']:.4f} mm (random) -> {pa['shape_rms_mm']:.4f} mm "
        f"(planned); max {pa['shape_max_mm']:.4f} mm",
        f"travel {s['travel_rad']['grouped_by_target']:.2f} rad (grouped by target) -> "
        f"{s['travel_rad']['ordered']:.2f} rad (ordered); selection "
        f"{s['seconds']['selection']:.2f} s, total {s['seconds']['total']:.1f} s",
    ]


#: a plan whose identification Jacobian is worse conditioned than this is refused (exit 3):
#: well-planned cells give 1e3-1e4, a rank-deficient one 1e17
MAX_PLAN_COND = 1e8


@click.command(
    "plan",
    epilog="""\b
Examples:
  vtcal plan --urdf lrmate --targets datasets/targets/lrmate_cell.csv --poses 36 \\
      --pin 0.047,0.002,0.251 --out plan.parquet
  vtcal plan --urdf ur5e --targets datasets/targets/ur5e_cell.csv --poses 24 --out ur.parquet
""",
)
@click.option("--urdf", required=True, help="Robot: URDF file, or built-in lrmate/ur5e/iiwa7.")
@click.option(
    "--targets",
    "targets_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="CSV: target_id, x, y, z (approximate centre, base frame, m), nx, ny, nz (plate normal).",
)
@click.option("--poses", type=int, required=True, help="Number of measuring poses to choose.")
@click.option(
    "--out", required=True, type=click.Path(dir_okay=False, path_type=Path), help="PLAN.parquet"
)
@click.option("--base-link", default="base_link", show_default=True)
@click.option("--flange-link", default="flange", show_default=True)
@click.option(
    "--pin",
    default="0,0,0.2",
    show_default=True,
    callback=_parse_xyz,
    help="Approximate virtual pin in the flange frame, X,Y,Z metres (the camera looks along "
    "flange z; the pin is the stand-off point it touches).",
)
@click.option(
    "--cone-deg",
    type=float,
    default=35.0,
    show_default=True,
    help="Largest angle between the view axis and the plate normal.",
)
@click.option(
    "--roll-deg",
    type=float,
    default=180.0,
    show_default=True,
    help="Rolls about the view axis drawn in +-this range.",
)
@click.option("--candidates", type=int, default=2000, show_default=True)
@click.option(
    "--criterion",
    type=click.Choice(["O1", "O3", "O4", "A"]),
    default="O1",
    show_default=True,
    help="O1 D-optimal, O3 min singular value, O4 noise amplification, A A-optimal.",
)
@click.option(
    "--model", default="full", show_default=True, help=f"Error model: {', '.join(model_names())}."
)
@click.option(
    "--sigma-mm",
    type=float,
    default=0.01,
    show_default=True,
    help="Touch-up contact noise per axis, mm (for the predicted error).",
)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--quiet", is_flag=True, help="Print nothing on success.")
def command(
    urdf: str,
    targets_path: Path,
    poses: int,
    out: Path,
    base_link: str,
    flange_link: str,
    pin: tuple[float, float, float],
    cone_deg: float,
    roll_deg: float,
    candidates: int,
    criterion: str,
    model: str,
    sigma_mm: float,
    seed: int,
    quiet: bool,
) -> None:
    """Plan measuring poses that make the identification well conditioned."""
    from pipeline.io.artefacts import write_artefact
    from pipeline.plan.planner import PlanConfig, plan_poses
    from pipeline.plan.targets import read_targets
    from pipeline.robots import load_urdf

    urdf_xml = load_urdf(urdf)
    targets = read_targets(targets_path)
    config = PlanConfig(
        n_poses=poses,
        n_candidates=candidates,
        cone_deg=cone_deg,
        roll_deg=roll_deg,
        p_flange_pin=pin,
        criterion=criterion,
        model=model,
        seed=seed,
        sigma_m=sigma_mm * 1e-3,
    )
    res = plan_poses(
        urdf_xml,
        targets,
        config,
        base_link=base_link,
        flange_link=flange_link,
        where=str(targets_path),
    )
    if out.parent and not out.parent.exists():
        raise BadInput(f"{out}: folder {out.parent} does not exist")
    cond = float(res.summary["indices_after"]["cond"])
    if not cond < MAX_PLAN_COND:
        from pipeline.errors import CalibrationFailed

        raise CalibrationFailed(
            f"{out}: not written: the {res.summary['n_poses']} planned poses leave the "
            f"identification rank deficient (condition number {cond:.3g} > {MAX_PLAN_COND:g}; "
            f"{res.summary['n_identifiable']} of {res.summary['n_params']} parameter directions "
            "identifiable), so no predicted error would mean anything: plan more poses "
            "(--poses) or a smaller error model (--model offsets)"
        )
    write_artefact(
        out,
        res.table,
        "plan",
        stage="plan",
        config=res.summary["config"],
        extra_meta={
            "plan": json.dumps(res.summary, default=float),
            "joint_names": json.dumps(res.summary["joint_names"]),
        },
    )
    if not quiet:
        for line in _summary_lines(res.summary, out):
            click.echo(line)
