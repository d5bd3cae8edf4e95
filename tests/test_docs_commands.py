"""Docs as tests: every command README.md, docs/*.md and each ``--help`` show runs as written.

Issue 35: a user following the docs met commands that failed as written and figures that
no longer matched the run. Here each doc's commands (``support/doc_commands.py`` finds
and classifies them) run in order, as ``vtcal`` would on a fresh clone, in one sandbox
folder holding the repository's ``datasets/`` and ``pipeline/robots/``; each must exit
with the status its text implies, and each output block (``<!-- output -->`` before a
code block) must be what its command printed: the figures the docs quote from a run
are checked against the run that prints them.

The shipped sample's run (``vtcal run datasets/samples/sample_lrmate.mcap --out
runs/sample``, ~16 s) is made once for all. Long commands (a whole simulated cell, a
batch, a cell) run only with ``VTCAL_DOCS_LONG=1``; synopses, live-cell commands and
commands on the reader's own files are counted, not run. The last test prints the
counts and fails if a doc's command fell out of the runner.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from support.doc_commands import Command, all_commands, is_long, kind, matches, missing_inputs

REPO = Path(__file__).resolve().parent.parent
LONG = os.environ.get("VTCAL_DOCS_LONG") == "1"
SAMPLE_RUN = "vtcal run datasets/samples/sample_lrmate.mcap --out runs/sample"
COMMANDS = all_commands(REPO)
TALLY: Counter[str] = Counter()


def _vtcal(cmd: Command, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"}
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *cmd.args],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh clone's view: datasets/ (its files linked, its manifests copied: a batch writes
    beside them), pipeline/robots, and the shipped sample's run in runs/sample."""
    root = tmp_path_factory.mktemp("docs")
    data = root / "datasets"
    data.mkdir()
    for p in (REPO / "datasets").iterdir():
        if p.suffix == ".toml":
            (data / p.name).write_text(p.read_text())
        else:
            (data / p.name).symlink_to(p)
    (root / "pipeline").mkdir()
    (root / "pipeline" / "robots").symlink_to(REPO / "pipeline" / "robots")
    sample = Command("sandbox", SAMPLE_RUN)
    res = _vtcal(sample, root)
    assert res.returncode == 0, res.stderr
    (root / "sample_run.out").write_text(res.stdout + res.stderr)
    return root


def _run_file(name: str, cmds: list[Command], cwd: Path) -> list[str]:
    """Run a doc's commands in order; the problems found (empty: all as the text says)."""
    problems: list[str] = []
    background: list[subprocess.Popen[bytes]] = []
    last: str | None = None
    try:
        for cmd in cmds:
            k = kind(cmd)
            if k != "run":
                TALLY[k] += 1
                continue
            if cmd.text == SAMPLE_RUN and not cmd.background:
                printed = (cwd / "sample_run.out").read_text()  # the sandbox made it
                TALLY["run"] += 1
            elif is_long(cmd) and not LONG:
                TALLY["long"] += 1
                continue
            elif missing_inputs(cmd, cwd):
                TALLY["user file"] += 1
                continue
            elif "tcp://127.0.0.1" in cmd.text and not background:  # a cell served before
                TALLY["live cell"] += 1
                continue
            elif cmd.background or cmd.args[0] == "cell-server":  # a server runs until stopped
                background.append(_start(cmd, cwd))
                TALLY["run"] += 1
                continue
            else:
                res = _vtcal(cmd, cwd)
                TALLY["run"] += 1
                printed = res.stdout + res.stderr
                if res.returncode != cmd.exit_code:
                    problems.append(
                        f"{cmd.source}: `{cmd.text}` exited {res.returncode}, the text implies "
                        f"{cmd.exit_code}: {res.stderr.strip()[-300:]}"
                    )
            last = printed
            if cmd.output:
                TALLY["output blocks"] += 1
                TALLY["figures"] += sum(any(ch.isdigit() for ch in ln) for ln in cmd.output)
                missing = matches(cmd.output, last)
                if missing:
                    problems.append(
                        f"{cmd.source}: `{cmd.text}` did not print, in this order: {missing}"
                    )
    finally:
        for proc in background:
            proc.terminate()
            proc.wait(timeout=30)
    return problems


def _start(cmd: Command, cwd: Path) -> subprocess.Popen[bytes]:
    import time

    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *cmd.args], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    time.sleep(5.0)  # a server: let it listen (and write its --plan-out) first
    return proc


def _folder_of(name: str, sandbox: Path) -> Path:
    """A fresh folder for one doc: the sandbox's datasets/, pipeline/ and runs/sample linked
    in, nothing another doc wrote (a doc's rec.mcap is its own)."""
    slug = "".join(ch if ch.isalnum() else "_" for ch in name)
    d = sandbox / "docs" / slug
    (d / "runs").mkdir(parents=True)
    for sub in ("datasets", "pipeline"):
        (d / sub).symlink_to(sandbox / sub)
    (d / "runs" / "sample").symlink_to(sandbox / "runs" / "sample")
    (d / "sample_run.out").symlink_to(sandbox / "sample_run.out")
    return d


@pytest.mark.parametrize("name", list(COMMANDS))
def test_the_commands_run_as_written(name: str, sandbox: Path) -> None:
    problems = _run_file(name, COMMANDS[name], _folder_of(name, sandbox))
    assert not problems, "\n".join(problems)


def test_every_help_has_a_runnable_example(sandbox: Path) -> None:
    """Each command's ``--help`` shows one example that runs on the shipped data as written
    (fast ones here; the long ones only need shipped inputs, or files an example before
    them writes)."""
    lacking = []
    made: set[str] = {"runs/sample"}
    for name, cmds in COMMANDS.items():
        if not name.endswith("--help"):
            continue
        ok = False
        for cmd in cmds:
            if kind(cmd) != "run":
                continue
            missing = [m for m in missing_inputs(cmd, sandbox) if m not in made]
            if not missing:
                ok = True
            args = cmd.args
            for opt in ("--out", "--plan-out"):
                if opt in args:
                    made.add(args[args.index(opt) + 1].rstrip("/"))
        if not ok:
            lacking.append(name)
    assert not lacking, f"no runnable example: {lacking}"


def test_the_docs_quote_the_sample_as_it_runs(sandbox: Path) -> None:
    """The figures of the shipped sample the docs quote are the run's: its verdict line
    (model and validated figure) is in README.md, as the run printed it."""
    printed = (sandbox / "sample_run.out").read_text()
    verdict = next(ln.strip() for ln in printed.splitlines() if "verdict: model" in ln)
    readme = (REPO / "README.md").read_text()
    assert verdict in readme, verdict
    model = verdict.split("model ", 1)[1].split(":", 1)[0]
    figure = verdict.split(": ", 2)[2].split(" mm", 1)[0]
    export = (REPO / "docs" / "export.md").read_text()
    assert f"shipped model: {model} (chosen by held-out error)" in export
    assert f"validated accuracy: {figure} mm RMS held-out" in export
    assert f"with the shipped model {model}" in export


def summary_line() -> str:
    """The runner's counts (conftest.py prints it at the end of every session that ran it)."""
    found = sum(len(c) for c in COMMANDS.values())
    return (
        f"docs as tests: {found} commands in {len(COMMANDS)} docs and --help texts: "
        f"{TALLY['run']} run, {TALLY['long']} long (VTCAL_DOCS_LONG=1), "
        f"{TALLY['user file']} on the reader's files, {TALLY['synopsis']} synopses, "
        f"{TALLY['live cell']} live cell; {TALLY['figures']} quoted lines with figures "
        f"checked in {TALLY['output blocks']} output blocks"
    )


def test_zz_counts(sandbox: Path) -> None:
    """What the runner did: it ran commands and checked figures."""
    line = summary_line()
    print(line)
    (sandbox / "counts.txt").write_text(line + "\n")
    if TALLY["run"]:  # the whole module ran (not one file alone with -k)
        assert TALLY["run"] >= 15 and TALLY["figures"] >= 3, line


def test_the_runner_sees_what_it_must() -> None:
    """Negative controls: a synopsis, a live cell, the reader's file, a wrong exit."""
    from support.doc_commands import commands_in_text

    cmds = commands_in_text(
        [
            "    vtcal run REC.mcap --out DIR",
            "    vtcal measure --plan p.parquet --robot tcp://10.0.0.2:30010 --out r.mcap",
            "    vtcal compare runs/a runs/b --fail-on-drift   # exit 1 on drift",
            "vtcal run not/a/block.mcap --out x",
            "    vtcal version: 0.1.0",
            "<!-- output -->",
            "    improved x... over",
        ],
        "t.md",
    )
    assert [kind(c) for c in cmds] == ["synopsis", "live cell", "run"]
    assert cmds[2].exit_code == 1 and cmds[2].output == ["improved x... over"]
    assert matches(["improved x... over"], "a\nimproved x20.3 over\n") == []
    assert matches(["b", "a"], "a\nb\n") == ["a"]
    assert shlex.split(cmds[0].text)[0] == "vtcal"
