"""The commands the docs show, and the outputs they quote (``tests/test_docs_commands.py``).

A *command* is a line starting with ``vtcal `` in a code block of a Markdown file (an
indented block, or a fenced one without a language or marked sh/bash/console), joined
over trailing backslashes, or a line of a command's ``--help`` examples. A trailing
``# comment`` is dropped; ``# exit N`` in it is the exit status the text implies
(default 0). A trailing ``&`` runs it in the background until the file's commands end.

An *output block* is a code block right after the Markdown comment ``<!-- output -->``:
its lines are what the last command run above it in the same file printed (stdout then
stderr), in order, other lines in between allowed; ``...`` in a line stands for any text.

Each command is put in one class:

- ``synopsis``: it has placeholders (``REC.mcap``, ``DIR``, ``[--out FILE]``, ``A|B``, ...);
- ``live cell``: it talks to real hardware (a camera, a controller's address);
- ``run``: everything else, run as written in a sandbox holding the repository's
  ``datasets/`` and ``pipeline/robots/``. A command whose input file does not exist there
  (the reader's own recording, ``rec1.mcap``) is not run and counted as ``user file``;
  a long one (a simulation of a whole cell, a batch, a cell) is run only with
  ``VTCAL_DOCS_LONG=1`` and counted as ``long`` otherwise.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

#: fenced-block languages whose ``vtcal`` lines are commands
SHELL_FENCES = ("", "sh", "bash", "console", "shell")
#: options whose value is a file or folder the command reads
INPUT_OPTIONS = ("--plan", "--targets", "--manifest", "--scenario", "--urdf")
#: an uppercase placeholder: REC.mcap, RUN_DIR, TABLE.csv, CALIBRATED.urdf, HOST, DIR
PLACEHOLDER = re.compile(r"(^|[/:=,])[A-Z][A-Z0-9_]*[A-Z0-9](\.[a-z0-9]+)?($|[/:=,.])")
#: what makes a command a synopsis rather than something to type
SYNOPSIS_MARKS = re.compile(r"[\[\]{}|]|\.\.\.|\bS1\b")


@dataclass
class Command:
    """One command of a doc, where it is and what its text implies."""

    source: str  # file (or "vtcal CMD --help") and line
    text: str  # as shown, without its comment
    exit_code: int = 0
    background: bool = False
    output: list[str] = field(default_factory=list)  # the output block after it, if any

    @property
    def args(self) -> list[str]:
        """The arguments after ``vtcal``."""
        return shlex.split(self.text)[1:]


def _strip_comment(line: str) -> tuple[str, int]:
    """``(command, exit status)`` of a line with an optional trailing ``# comment``."""
    m = re.search(r"\s+#\s?(.*)$", line)
    code = 0
    if m:
        e = re.search(r"\bexit(?: status)? (\d+)", m.group(1))
        code = int(e.group(1)) if e else 0
        line = line[: m.start()]
    return line.strip(), code


def _is_command(line: str) -> bool:
    """``vtcal SUBCOMMAND ...`` (``$ `` allowed before), SUBCOMMAND one of vtcal's."""
    from pipeline.cli import COMMANDS

    m = re.match(r"^(?:\$ )?vtcal ([a-z-]+)(\s|$)", line)
    return bool(m) and m.group(1) in COMMANDS


def _command(text: str, source: str) -> Command:
    text, code = _strip_comment(text)
    bg = text.endswith("&")
    return Command(source, text.rstrip("&").strip(), code, bg)


def commands_in_text(lines: list[str], name: str) -> list[Command]:
    """Commands and output blocks of a Markdown file's lines (see the module doc)."""
    out: list[Command] = []
    fence: str | None = None
    want_output = False
    collecting: list[str] | None = None
    i = 0
    while i < len(lines):
        raw = lines[i]
        s = raw.strip()
        if s.startswith("```"):
            if fence is None:
                fence = s[3:].strip()
                if want_output:
                    collecting, want_output = [], False
            else:
                fence = None
                if collecting is not None and out:
                    out[-1].output = collecting
                collecting = None
            i += 1
            continue
        indented = raw.startswith(("    ", "\t")) and fence is None
        if s == "<!-- output -->":
            want_output = True
            i += 1
            continue
        if want_output and indented and s:  # an indented output block starts
            collecting, want_output = [], False
        if collecting is not None:
            if fence is not None or (indented or not s):
                if s:
                    collecting.append(s)
                i += 1
                continue
            if out:
                out[-1].output = collecting
            collecting = None
        if (indented or (fence is not None and fence in SHELL_FENCES)) and _is_command(s):
            start = i
            text = s.removeprefix("$ ")
            while text.endswith("\\") and i + 1 < len(lines):
                i += 1
                text = text[:-1].rstrip() + " " + lines[i].strip()
            out.append(_command(text, f"{name}:{start + 1}"))
        i += 1
    if collecting is not None and out:
        out[-1].output = collecting
    return out


def commands_in_help(name: str, epilog: str) -> list[Command]:
    """The ``vtcal ...`` example lines of a command's ``--help`` epilog."""
    lines = [ln for ln in epilog.splitlines() if ln.strip() != "\b"]
    return [
        c
        for c in commands_in_text(["    " + ln.strip() for ln in lines], f"vtcal {name} --help")
        if c.args[:1] == [name]
    ]


def kind(cmd: Command) -> str:
    """``synopsis``, ``live cell`` or ``run`` (see the module doc)."""
    if SYNOPSIS_MARKS.search(cmd.text):
        return "synopsis"
    values = [a for a in cmd.args[1:] if not a.startswith("-")]
    if any(PLACEHOLDER.search(v) for v in values):
        return "synopsis"
    live = ("opencv:", "folder:/data")
    tcp = re.findall(r"tcp://([^:/\s]+)", cmd.text)
    if any(x in cmd.text for x in live) or any(h not in ("127.0.0.1", "localhost") for h in tcp):
        return "live cell"
    return "run"


def inputs(cmd: Command) -> list[str]:
    """The files and folders the command reads (positional paths and input options)."""
    args = cmd.args
    got: list[str] = []
    i = 1
    while i < len(args):
        a = args[i]
        if a.startswith("-"):
            if a in INPUT_OPTIONS and i + 1 < len(args):
                got.append(args[i + 1])
            i += 1 if "=" in a or _is_flag(args, i) else 2
            continue
        if "/" in a or "." in a:
            got.append(a)
        i += 1
    return [g for g in got if not g.startswith(("sim:", "tcp:")) and g not in BUILT_IN_URDFS]


def missing_inputs(cmd: Command, cwd: Path) -> list[str]:
    """The inputs not in ``cwd`` (a glob such as ``runs/*`` counts as the reader's own)."""
    return [g for g in inputs(cmd) if "*" in g or not (cwd / g).exists()]


#: names ``--urdf`` takes besides a file (vtcal's built-in robots)
BUILT_IN_URDFS = ("lrmate", "ur5e", "iiwa7")
#: flags that take no value
FLAGS = {
    "--no-report", "--no-rrd", "--quiet", "-q", "--force", "--dry-run", "--fail-on-drift",
    "--no-crossval", "--accept-implausible", "--help", "-h",
}  # fmt: skip


def _is_flag(args: list[str], i: int) -> bool:
    return args[i] in FLAGS or i + 1 >= len(args) or args[i + 1].startswith("-")


#: subcommands that run in seconds on the shipped data (others are ``long``)
FAST = {"report", "export", "plan", "compare", "validate"}


def is_long(cmd: Command) -> bool:
    """A command that takes more than a few seconds (see :data:`FAST`)."""
    sub = cmd.args[0]
    if sub == "run":  # the shipped sample's run is made once for all (the sandbox's)
        return cmd.args[1:2] != ["datasets/samples/sample_lrmate.mcap"]
    if sub == "simulate":
        return "datasets/scenarios/small.toml" not in cmd.args
    if sub == "identify":
        return any("mukca" in a for a in cmd.args)
    return sub not in FAST


def matches(expected: list[str], printed: str) -> list[str]:
    """The lines of ``expected`` not found, in order, among the printed lines."""
    lines = [ln.strip() for ln in printed.splitlines()]
    missing = []
    j = 0
    for e in expected:
        pat = re.compile(".*".join(re.escape(p.strip()) for p in e.split("...")) + "$")
        k = j
        while k < len(lines) and not pat.match(lines[k]):
            k += 1
        if k == len(lines):
            missing.append(e)
        else:
            j = k + 1
    return missing


def doc_files(repo: Path) -> list[Path]:
    """README.md, then docs/*.md in name order."""
    return [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]


def all_commands(repo: Path) -> dict[str, list[Command]]:
    """Every doc's commands (key: its path from the repo), then every ``--help``'s."""
    import click

    from pipeline.cli import COMMANDS, cli

    out = {
        str(p.relative_to(repo)): commands_in_text(p.read_text().splitlines(), p.name)
        for p in doc_files(repo)
    }
    ctx = click.Context(cli)
    for name in sorted(COMMANDS):
        command = cli.get_command(ctx, name)
        assert command is not None, name
        out[f"vtcal {name} --help"] = commands_in_help(name, command.epilog or "")
    return out
