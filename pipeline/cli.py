"""The ``vtcal`` command line: one click group, one module per command.

Each command lives in ``pipeline/commands/NAME.py`` as a ``click.Command``
called ``command``; this module gathers them lazily (so ``vtcal --help`` does
not import rerun, opencv, ...) and turns every :class:`~pipeline.errors.VtcalError`
into one clear line on stderr and its exit code (see README, "Exit codes").
"""

from __future__ import annotations

import os
import sys
from typing import Any

from pipeline.run.threads import prefer_one_thread

prefer_one_thread()  # before numpy loads: see pipeline/run/threads.py

import click  # noqa: E402

from pipeline import __version__  # noqa: E402
from pipeline.errors import EXIT_INTERNAL, EXIT_INTERRUPTED, VtcalError  # noqa: E402
from pipeline.run.lazy import Ref  # noqa: E402

#: command name -> (its ``command``, imported when used; one-line help shown in ``vtcal --help``)
COMMANDS: dict[str, tuple[Ref, str]] = {
    "simulate": (
        Ref("pipeline.commands.simulate", "command"),
        "Simulate a touch-up recording with ground truth.",
    ),
    "run": (
        Ref("pipeline.commands.run", "command"),
        "Calibrate from a recording: every stage, end to end.",
    ),
    "identify": (
        Ref("pipeline.commands.identify", "command"),
        "Identify kinematics from a touch-up table.",
    ),
    "report": (
        Ref("pipeline.commands.report", "command"),
        "Re-render report.html and run.rrd from a run folder.",
    ),
    "plan": (Ref("pipeline.commands.plan", "command"), "Plan well-conditioned measuring poses."),
    "compare": (
        Ref("pipeline.commands.compare", "command"),
        "Compare runs: held-out error, parameters, drift.",
    ),
    "batch": (
        Ref("pipeline.commands.batch", "command"),
        "Run many recordings, cached, in parallel.",
    ),
    "audit": (
        Ref("pipeline.commands.audit", "command"),
        "Robots over time: drift, what changed, models ranked.",
    ),
    "validate": (
        Ref("pipeline.commands.validate", "command"),
        "Judge a calibrated URDF on another recording's touch-ups.",
    ),
    "export": (
        Ref("pipeline.commands.export", "command"),
        "Write a run's calibration for a controller or ROS.",
    ),
    "predict": (
        Ref("pipeline.commands.predict", "command"),
        "Where the calibrated robot puts its tool at joints.",
    ),
    "compensate": (
        Ref("pipeline.commands.compensate", "command"),
        "Joints that reach targets on the calibrated robot.",
    ),
    "measure": (
        Ref("pipeline.commands.measure", "command"),
        "Run a plan on a cell: touch up and record.",
    ),
    "calibrate": (
        Ref("pipeline.commands.calibrate", "command"),
        "Plan -> measure -> run for a cell, in one go.",
    ),
    "cell-server": (
        Ref("pipeline.commands.cell_server", "command"),
        "Serve the simulated cell over the cell protocol (TCP).",
    ),
}


class LazyGroup(click.Group):
    """A group whose sub-commands are imported only when used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return [n for n, (ref, _) in COMMANDS.items() if ref.exists()]

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS or cmd_name not in self.list_commands(ctx):
            return None
        cmd: click.Command = COMMANDS[cmd_name][0].load()
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


def _caused_by_interrupt(exc: BaseException) -> bool:
    """True if a KeyboardInterrupt is in the exception's cause/context chain.

    Ctrl-C landing inside a C extension's import (rerun, numba, ...) surfaces
    as an ImportError whose context is the KeyboardInterrupt.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _interrupted(standalone: bool) -> None:
    """Say so in one line and exit 130.

    As the real command (``standalone``) it leaves through ``os._exit`` after
    flushing: every artefact is already complete (writes are atomic), and a
    half-initialised extension module interrupted mid-import can crash the
    interpreter's own finalisation.
    """
    click.echo("vtcal: interrupted; finished artefacts are intact", err=True)
    if standalone:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_INTERRUPTED)
    sys.exit(EXIT_INTERRUPTED)


def one_line(text: str) -> str:
    """The message on one line: every run of blanks that holds a line break becomes one space
    (a message quoting a value that prints over several lines stays one stderr line)."""
    return " ".join(text.split()) if "\n" in text or "\r" in text else text


def main(argv: list[str] | None = None) -> Any:
    """Entry point: run the CLI, mapping vtcal errors to one line and an exit code."""
    standalone = argv is None
    try:
        return cli.main(args=argv, prog_name="vtcal", standalone_mode=False)
    except click.exceptions.Abort:  # click turns Ctrl-C (KeyboardInterrupt) into Abort
        _interrupted(standalone)
    except click.UsageError as exc:  # bad option or argument: one line, like bad input
        cmd = exc.ctx.command_path if exc.ctx is not None else "vtcal"
        click.echo(f"vtcal: error: {exc.format_message()} (see '{cmd} --help')", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except VtcalError as exc:
        click.echo(f"vtcal: error: {one_line(str(exc))}", err=True)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        _interrupted(standalone)
    except Exception as exc:  # a bug, not bad input: one line, traceback on request
        if _caused_by_interrupt(exc):
            _interrupted(standalone)
        if os.environ.get("VTCAL_DEBUG"):
            raise
        where = exc.__traceback__
        while where is not None and where.tb_next is not None:
            where = where.tb_next
        loc = f" ({where.tb_frame.f_code.co_filename}:{where.tb_lineno})" if where else ""
        click.echo(
            f"vtcal: internal error: {type(exc).__name__}: {one_line(str(exc))}{loc}; "
            "set VTCAL_DEBUG=1 for the traceback and please report it",
            err=True,
        )
        sys.exit(EXIT_INTERNAL)


if __name__ == "__main__":  # python -m pipeline.cli, as python -m pipeline
    main()
