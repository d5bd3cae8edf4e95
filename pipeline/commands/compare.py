"""``vtcal compare RUN_DIR ...``: one table across runs and error models, and drift flags."""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.command(
    "compare",
    epilog="""\b
Examples:
  vtcal compare runs/sample                          # one run: its error models side by side
  vtcal compare runs/2024-05 runs/2024-11            # writes compare/compare.{parquet,html}
  vtcal compare runs/* --out audit.parquet --html audit.html --sigma 4
  vtcal compare runs/a runs/b --fail-on-drift        # exit status 5 when a parameter moved
""",
)
@click.argument("run_dirs", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("compare"),
              show_default=True,
              help="Folder for compare.parquet (the table, schemas/compare.json) and "
              "compare.html (created), or the table's own NAME.parquet (page: NAME.html).")  # fmt: skip
@click.option("--html", "html_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="The HTML page (default: beside the table, .html).")  # fmt: skip
@click.option("--sigma", "k_sigma", type=float, default=3.0, show_default=True,
              help="A parameter moved when |delta| > SIGMA * sqrt(std1^2 + std2^2).")  # fmt: skip
@click.option("--fail-on-drift", is_flag=True,
              help="Exit with status 5 when a parameter moved (0: none moved; 5 is not an "
              "error code: the comparison ran and its files are written).")  # fmt: skip
def command(
    run_dirs: tuple[Path, ...], out: Path, html_path: Path | None, k_sigma: float,
    fail_on_drift: bool,
) -> None:  # fmt: skip
    """Compare calibration runs (folders of `vtcal run` or `vtcal identify`).

    One table across datasets and error models: held-out error, parameter values
    and standard errors, condition, rejected touch-ups. Runs of the same robot
    (same nominal URDF) are compared with the first one given; a parameter that
    moved by more than its uncertainty is flagged.
    """
    from pipeline.accuracy.compare import compare_runs, heldout_text, render_html, told_apart_text
    from pipeline.errors import BadInput
    from pipeline.io.artefacts import atomic_write_bytes, write_artefact

    if not k_sigma > 0:
        raise BadInput(f"--sigma {k_sigma}: must be > 0")
    res = compare_runs(list(run_dirs), k_sigma=k_sigma)
    table = out if out.suffix == ".parquet" else out / "compare.parquet"
    table.parent.mkdir(parents=True, exist_ok=True)  # once the runs compared
    write_artefact(table, res.table, "compare", stage="compare", config={"k_sigma": k_sigma},
                   inputs={}, extra_meta={"runs": ",".join(res.summary["runs"])})  # fmt: skip
    page = html_path or table.with_suffix(".html")
    atomic_write_bytes(page, render_html(res).encode())
    for r in res.runs.itertuples():
        click.echo(
            f"{r.run:24s} {r.model:8s} held-out {heldout_text(r.heldout_rms_mm)}  training "
            f"{r.train_rms_mm:.4f} mm  cond {r.cond:.3g}  rejected {r.n_rejected}"
            + ("  (shipped)" if r.shipped else "")
            + told_apart_text(r.heldout_z_vs_shipped)
        )
    click.echo(res.summary["verdict"])
    for f in res.summary["flags"]:
        click.echo("  " + f)
    click.echo(f"table: {table}   page: {page}")
    if fail_on_drift and res.summary["flags"]:
        from pipeline.errors import EXIT_CHANGED

        n = len(res.summary["flags"])
        click.echo(f"vtcal compare: drift: {n} flag(s) above; exit {EXIT_CHANGED} "
                   "(--fail-on-drift)", err=True)  # fmt: skip
        sys.exit(EXIT_CHANGED)
