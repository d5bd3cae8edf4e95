"""Every ``vtcal ...`` line the docs show parses against the CLI as written.

``tests/test_docs_commands.py`` runs the commands it can; commands on the reader's own
files, long ones and synopses (``vtcal export RUN_DIR --format FORMAT [--out FILE]``) are
only counted there. Here each of them, from README.md, docs/*.md, the group's help and
every command's help and examples, is parsed by click the way ``vtcal`` would parse it
(``make_context`` on its sub-command, parameter types and callbacks included), without
running it: an option a command does not have, a flag given a value, a missing or extra
argument, or a recording argument that is a batch manifest fails here.

A synopsis is expanded first: ``[...]`` keeps what is inside, ``A|B`` takes ``A``,
``{csv,parquet}`` takes ``csv``, ``NAME...`` is ``NAME``, a lone ``...`` is dropped, and
``X | --opt V`` between two alternatives gives one command for each. A placeholder
(``X``, ``FORMAT``) given to a numeric or a choice option stands for a valid value. Input files need not
exist (``click.Path(exists=True)`` is not checked: the reader's files are not here).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import click
import pytest
from support.doc_commands import PLACEHOLDER, Command, commands_in_text, doc_files, kind

from pipeline.cli import COMMANDS, cli

REPO = Path(__file__).resolve().parent.parent


def _help_texts() -> dict[str, str]:
    """``vtcal --help``'s and each command's help and examples (docstring and epilog)."""
    ctx = click.Context(cli)
    out = {"vtcal --help": cli.help or ""}
    for name in sorted(COMMANDS):
        cmd = cli.get_command(ctx, name)
        assert cmd is not None, name
        out[f"vtcal {name} --help"] = f"{cmd.help or ''}\n{cmd.epilog or ''}"
    return out


def documented_commands() -> list[Command]:
    """Every ``vtcal SUBCOMMAND ...`` line of the docs and the help texts."""
    cmds: list[Command] = []
    for p in doc_files(REPO):
        cmds += commands_in_text(p.read_text().splitlines(), p.name)
    for name, text in _help_texts().items():
        lines = ["    " + ln.strip() for ln in text.splitlines() if ln.strip() != "\b"]
        cmds += commands_in_text(lines, name)
    return cmds


def expand(text: str) -> list[list[str]]:
    """The argument lists (after ``vtcal``) a command or synopsis stands for."""
    tokens = [t.replace("[", "").replace("]", "") for t in shlex.split(text)[1:]]
    return _alternatives([t for t in tokens if t and t != "..."])


def _alternatives(toks: list[str]) -> list[list[str]]:
    """``X | --opt V`` (a lone ``|`` between two alternatives): one list for each."""
    if "|" not in toks:
        return [_expand_tokens(toks)]
    i = toks.index("|")
    right = toks[i + 1 : i + 3] if toks[i + 1].startswith("-") else toks[i + 1 : i + 2]
    rest = toks[i + 1 + len(right) :]
    return _alternatives(toks[:i] + rest) + _alternatives(toks[: i - 1] + right + rest)


def _expand_tokens(tokens: list[str]) -> list[str]:
    out = []
    for t in tokens:
        t = re.sub(r"\{([^,}]*)[^}]*\}", r"\1", t)  # TABLE.{csv,parquet} -> TABLE.csv
        if "|" in t and not t.startswith(("tcp:", "sim:")):
            t = t.split("|", 1)[0]  # auto|full|mdh -> auto
        if t.endswith("...") and len(t) > 3 and not t.endswith(",..."):
            t = t[:-3]  # RECORDINGS... -> RECORDINGS
        out.append(t)
    return out


NUMERIC = (click.types.FloatParamType, click.types.IntParamType)


def parse(cmd: Command, monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Problems parsing ``cmd`` (empty: every variant parses)."""
    problems = []
    for args in expand(cmd.text):
        name, rest = args[0], args[1:]
        sub = cli.get_command(click.Context(cli), name)
        if sub is None:
            problems.append(f"{cmd.source}: `{cmd.text}`: no command {name!r}")
            continue
        if "--help" in rest or "-h" in rest:
            continue
        for p in sub.params:  # the reader's files are not here: names only
            if isinstance(p.type, click.Path) and p.type.exists:
                monkeypatch.setattr(p.type, "exists", False)
        if kind(cmd) == "synopsis":
            rest = _values_for_placeholders(sub, rest)
        parent = cli.make_context("vtcal", [name], resilient_parsing=False)
        try:
            sub.make_context(name, list(rest), parent=parent, resilient_parsing=False)
        except click.ClickException as exc:
            problems.append(f"{cmd.source}: `{cmd.text}`: {exc.format_message()}")
    return problems


def _values_for_placeholders(sub: click.Command, args: list[str]) -> list[str]:
    """A placeholder value (``X``, ``FORMAT``) of a numeric option becomes ``1``, of a
    choice its first choice."""
    typed: dict[str, str] = {}
    for p in sub.params:
        if isinstance(p, click.Option) and isinstance(p.type, NUMERIC):
            typed.update(dict.fromkeys(p.opts, "1"))
        elif isinstance(p, click.Option) and isinstance(p.type, click.Choice):
            typed.update(dict.fromkeys(p.opts, str(p.type.choices[0])))
    out = list(args)
    for i in range(len(out) - 1):
        if out[i] in typed and (PLACEHOLDER.search(out[i + 1]) or out[i + 1].isupper()):
            out[i + 1] = typed[out[i]]
    return out


COMMANDS_DOCUMENTED = documented_commands()


@pytest.mark.parametrize(
    "cmd", COMMANDS_DOCUMENTED, ids=[f"{c.source}:{c.text[:50]}" for c in COMMANDS_DOCUMENTED]
)
def test_each_documented_command_parses(cmd: Command, monkeypatch: pytest.MonkeyPatch) -> None:
    problems = parse(cmd, monkeypatch)
    assert not problems, "\n".join(problems)


def test_the_docs_and_helps_show_commands_and_synopses() -> None:
    kinds = {kind(c) for c in COMMANDS_DOCUMENTED}
    sources = {c.source.split(":")[0] for c in COMMANDS_DOCUMENTED}
    assert len(COMMANDS_DOCUMENTED) >= 80 and {"run", "synopsis"} <= kinds
    assert {"README.md", "audit.md", "vtcal audit --help", "vtcal --help"} <= sources


@pytest.mark.parametrize(
    "text, wrong",
    [
        ("vtcal batch fleet.toml --out fleet_runs/ --until outliers", "use --manifest"),
        ("vtcal run rec.mcap --out runs/rec --modle full", "No such option"),
        ("vtcal report runs/sample extra", "unexpected extra argument"),
        ("vtcal export --format urdf", "Missing argument"),
        ("vtcal export RUN_DIR --format FORMAT [--outt FILE]", "No such option"),
        ("vtcal run rec.mcap --out runs/x --tolerance-mm -1", "--tolerance-mm"),
        ("vtcal compare --fail-on-drift", "Missing argument"),
        ("vtcal plan --urdf lrmate --out plan.parquet --no-report", "No such option"),
    ],
)
def test_a_wrong_command_fails_to_parse(
    text: str, wrong: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Negative controls: what a doc could get wrong is caught."""
    (cmd,) = commands_in_text(["    " + text], "t.md")
    problems = parse(cmd, monkeypatch)
    assert problems and wrong in problems[0], problems


def test_synopses_expand_to_each_alternative() -> None:
    assert expand("vtcal batch RECORDINGS... | --manifest datasets/NAME.toml  --out DIR") == [
        ["batch", "RECORDINGS", "--out", "DIR"],
        ["batch", "--manifest", "datasets/NAME.toml", "--out", "DIR"],
    ]
    assert expand(
        "vtcal identify TABLE.{csv,parquet} --model auto|full [--distance A:B=M ...]"
    ) == [["identify", "TABLE.csv", "--model", "auto", "--distance", "A:B=M"]]
