"""The ``vtcal`` command line: one click group, one module per command.

Each command lives in ``pipeline/commands/NAME.py`` as a ``click.Command``
called ``command``; this module gathers them lazily (so ``vtcal --help`` does
not import rerun, opencv, ...) and turns every :class:`~pipeline.errors.VtcalError`
into one clear line on stderr and its exit code (see README, "Exit codes").
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from typing import Any

import click

from pipeline import __version__
from pipeline.errors import VtcalError

#: command name -> (module, one-line help shown in ``vtcal --help``)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("pipeline.commands.simulate", "Simulate a touch-up recording with ground truth."),
    "run": ("pipeline.commands.run", "Calibrate from a recording: every stage, end to end."),
    "identify": ("pipeline.commands.identify", "Identify kinematics from a touch-up table."),
    "report": ("pipeline.commands.report", "Re-render report.html and run.rrd from a run folder."),
    "plan": ("pipeline.commands.plan", "Plan well-conditioned measuring poses."),
    "compare": ("pipeline.commands.compare", "Compare runs: held-out error, parameters, drift."),
    "batch": ("pipeline.commands.batch", "Run many recordings, cached, in parallel."),
}


class LazyGroup(click.Group):
    """A group whose sub-commands are imported only when used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return [n for n, (mod, _) in COMMANDS.items() if importlib.util.find_spec(mod)]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS or cmd_name not in self.list_commands(ctx):
            return None
        mod = importlib.import_module(COMMANDS[cmd_name][0])
        cmd: click.Command = mod.command
        return cmd

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(n, COMMANDS[n][1]) for n in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


@click.group(
    cls=LazyGroup,
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
)
@click.version_option(__version__, prog_name="vtcal")
def cli() -> None:
    """vtcal: calibrate a robot's kinematics from visual touch-up recordings.

    \b
    Typical use:
      vtcal simulate --scenario datasets/scenarios/standard.toml --seed 1 --out rec.mcap
      vtcal run rec.mcap --out runs/rec
      vtcal identify touchups.csv --urdf robot.urdf --out runs/table
    """


def main(argv: list[str] | None = None) -> Any:
    """Entry point: run the CLI, mapping vtcal errors to one line and an exit code."""
    try:
        return cli.main(args=argv, prog_name="vtcal", standalone_mode=False)
    except click.exceptions.Abort:  # click turns Ctrl-C (KeyboardInterrupt) into Abort
        click.echo("vtcal: interrupted; finished artefacts are intact", err=True)
        sys.exit(130)
    except click.UsageError as exc:  # bad option or argument: one line, like bad input
        cmd = exc.ctx.command_path if exc.ctx is not None else "vtcal"
        click.echo(f"vtcal: error: {exc.format_message()} (see '{cmd} --help')", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except VtcalError as exc:
        click.echo(f"vtcal: error: {exc}", err=True)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        click.echo("vtcal: interrupted; finished artefacts are intact", err=True)
        sys.exit(130)
    except Exception as exc:  # a bug, not bad input: one line, traceback on request
        if os.environ.get("VTCAL_DEBUG"):
            raise
        where = exc.__traceback__
        while where is not None and where.tb_next is not None:
            where = where.tb_next
        loc = f" ({where.tb_frame.f_code.co_filename}:{where.tb_lineno})" if where else ""
        click.echo(
            f"vtcal: internal error: {type(exc).__name__}: {exc}{loc}; "
            "set VTCAL_DEBUG=1 for the traceback and please report it",
            err=True,
        )
        sys.exit(70)
