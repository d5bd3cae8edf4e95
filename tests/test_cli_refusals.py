"""Bad input is refused before any work, in one line, leaving nothing behind; every exit
status the CLI can return is in README's exit-code table.

- A non-positive (or not finite) ``--tolerance-mm`` is refused by every command that takes
  one (``vtcal run`` accepted -1, ran, judged FAIL and saved it).
- An empty or foreign recording file is refused from its first bytes, before numba,
  rerun or numpy load (a 0-byte file took 4.8 s and said ``bad magic b''``), naming the
  file, what was expected and what was found, and no run folder (nor its parent) is left.
- A batch manifest given as a recording is refused before the batch starts (it was read
  as a recording, failed late and left ``summary.parquet``).
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.cli import main

REPO = Path(__file__).resolve().parent.parent


def _vtcal(args: list[str], cwd: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"}
    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, "-m", "pipeline", *args],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    return res, time.perf_counter() - t0


TOLERANCE_COMMANDS = {
    "run": ["run", "rec.mcap", "--out", "runs/x"],
    "identify": ["identify", "t.csv", "--urdf", "lrmate", "--out", "runs/t"],
    "validate": ["validate", "cal.urdf", "rec.mcap"],
    "report": ["report", "runs/x"],
    "audit": ["audit", "runs/x"],
}


@pytest.mark.parametrize("value", ["-1", "0", "nan", "-inf", "abc"])
@pytest.mark.parametrize("name", list(TOLERANCE_COMMANDS))
def test_a_non_positive_tolerance_is_refused_by_every_command(
    name: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main([name, f"--tolerance-mm={value}", *TOLERANCE_COMMANDS[name][1:]])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2, err
    assert len(err.splitlines()) == 1 and "--tolerance-mm" in err, err
    assert "positive number" in err or "not a number" in err, err


def test_every_tolerance_option_is_checked() -> None:
    """Each command with a --tolerance-mm is in the test above."""
    import click

    from pipeline.cli import COMMANDS, cli

    ctx = click.Context(cli)
    have = {
        n
        for n in COMMANDS
        if any("--tolerance-mm" in p.opts for p in cli.get_command(ctx, n).params)  # type: ignore[union-attr]
    }
    assert have == set(TOLERANCE_COMMANDS)


FOREIGN = {
    "empty.mcap": (
        b"",
        "not an MCAP file: empty file (0 bytes); expected an MCAP recording or a ROS bag",
    ),
    "table.mcap": (b"joint_1,joint_2\n0.1,0.2\n", "text starting 'joint_1,joint_2'"),
    "archive.mcap": (b"PK\x03\x04" + bytes(60), "a ZIP archive (64 bytes)"),
    "noise.bag": (bytes(range(7, 71)), "not a ROS 1 bag: 64 bytes starting"),
}


@pytest.mark.parametrize("name", list(FOREIGN))
def test_an_empty_or_foreign_file_is_refused_at_once(name: str, tmp_path: Path) -> None:
    data, said = FOREIGN[name]
    (tmp_path / name).write_bytes(data)
    res, took = _vtcal(["run", name, "--out", "runs/x"], tmp_path)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0].startswith(f"vtcal: error: {name}: ") and said in lines[0], lines[0]
    assert not (tmp_path / "runs").exists()  # neither the run folder nor its parent
    assert took < 3.0, f"{took:.2f} s to refuse {name}"  # ~0.3 s over the interpreter's start


def test_the_refusal_loads_no_numeric_library(tmp_path: Path) -> None:
    (tmp_path / "x.mcap").write_bytes(b"")
    code = (
        "import sys\nfrom pipeline.cli import main\n"
        "try:\n    main(['run', 'x.mcap', '--out', 'runs/x'])\nexcept SystemExit as e:\n"
        "    print(e.code)\n"
        "print(sorted(m for m in ('numpy', 'numba', 'rerun', 'pandas', 'scipy', 'cv2', 'mcap')"
        " if m in sys.modules))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=120,
    )  # fmt: skip
    assert res.stdout.split() == ["2", "[]"], res.stdout + res.stderr


def test_a_bag_named_as_mcap_says_so(tmp_path: Path) -> None:
    from pipeline.errors import BadInput
    from pipeline.io.layout import locate

    (tmp_path / "cell.mcap").write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(BadInput, match=r"cell.mcap: not an MCAP file: a ROS 1 bag .* name it .bag"):
        locate(tmp_path / "cell.mcap")


def test_a_refused_run_removes_the_parents_it_made(tmp_path: Path) -> None:
    """A refusal after the check (here: no URDF in an MCAP that is only its magic) leaves
    no empty folder: neither --out nor the parents the run made for it."""
    (tmp_path / "m.mcap").write_bytes(b"\x89MCAP0\r\n")
    (tmp_path / "kept").mkdir()
    res, _ = _vtcal(["run", "m.mcap", "--out", "a/b/run", "--quiet"], tmp_path)
    assert res.returncode == 2, res.stderr
    assert not (tmp_path / "a").exists()
    res, _ = _vtcal(["run", "m.mcap", "--out", "kept/run", "--quiet"], tmp_path)
    assert res.returncode == 2 and (tmp_path / "kept").is_dir()
    assert not (tmp_path / "kept" / "run").exists()


def test_a_manifest_given_as_a_recording_is_refused_before_the_batch(tmp_path: Path) -> None:
    (tmp_path / "fleet.toml").write_text('[[recording]]\nname = "a"\npath = "a.mcap"\n')
    res, took = _vtcal(
        ["batch", "fleet.toml", "--out", "fleet_runs/", "--until", "outliers"], tmp_path
    )
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        "vtcal: error: fleet.toml looks like a manifest (TOML), not a recording: use "
        "--manifest fleet.toml (see 'vtcal batch --help')"
    ]
    assert not (tmp_path / "fleet_runs").exists() and res.stdout == ""


# ------------------------------------------------------------------ the exit-code table


def readme_exit_codes() -> set[int]:
    """The codes of README.md's "## Exit codes" table (its first column)."""
    text = (REPO / "README.md").read_text()
    m = re.search(r"^## Exit codes\s*$(.*?)(?=^## )", text, re.M | re.S)
    assert m, 'README.md has no "## Exit codes" section'
    return {int(c) for c in re.findall(r"^\|\s*(\d+)\s*\|", m.group(1), re.M)}


def codes_in_code(source: str, names: dict[str, int]) -> set[int]:
    """Exit statuses a module's code can end with: ``sys.exit(N)``, ``os._exit(N)``,
    ``SystemExit(N)``, ``ctx.exit(N)`` and ``exit_code = N`` (an error class's), with N a
    literal or an ``EXIT_*`` name of :mod:`pipeline.errors`."""
    found: set[int] = set()

    def value(node: ast.AST) -> int | None:
        if isinstance(node, ast.Constant) and isinstance(node.value, int):
            return int(node.value)
        if isinstance(node, ast.Name) and node.id in names:
            return names[node.id]
        if isinstance(node, ast.Attribute) and node.attr in names:
            return names[node.attr]
        return None

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and node.args:
            f = node.func
            callee = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if callee in ("exit", "_exit", "SystemExit"):
                v = value(node.args[0])
                if v is not None:
                    found.add(v)
        elif isinstance(node, ast.ClassDef):
            for stmt in node.body:
                if (
                    isinstance(stmt, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == "exit_code" for t in stmt.targets)
                    and value(stmt.value) is not None
                ):
                    found.add(value(stmt.value))  # type: ignore[arg-type]
    return found


def test_every_exit_code_is_in_the_readme_table() -> None:
    """The codes :mod:`pipeline.errors` defines and the ones the code exits with (scanned)
    are each a row of README's table, and the table lists no other."""
    from pipeline import errors

    names = {k: v for k, v in vars(errors).items() if k.startswith("EXIT_") and isinstance(v, int)}
    in_code: dict[int, list[str]] = {}
    for path in sorted((REPO / "pipeline").rglob("*.py")):
        for c in codes_in_code(path.read_text(), names):
            in_code.setdefault(c, []).append(str(path.relative_to(REPO)))
    undeclared = {c: w for c, w in in_code.items() if c not in errors.EXIT_CODES}
    assert not undeclared, f"exit codes not in pipeline.errors.EXIT_CODES: {undeclared}"
    assert {2, 3, 5, 70, 130} <= set(in_code), in_code  # the scan sees them
    table = readme_exit_codes()
    missing = {c: errors.EXIT_CODES[c] for c in sorted(set(errors.EXIT_CODES) - table)}
    assert not missing, f"README's exit-code table lacks {missing}"
    assert table <= set(errors.EXIT_CODES), f"README lists codes vtcal never returns: {table}"


def test_the_scan_sees_every_way_to_exit() -> None:
    src = (
        "import sys, os\nclass E(Exception):\n    exit_code = 9\n"
        "def f(ctx):\n    sys.exit(EXIT_X)\n    os._exit(11)\n    raise SystemExit(12)\n"
        "    ctx.exit(13)\n    sys.exit(errors.EXIT_Y)\n    sys.exit(code)\n"
    )
    assert codes_in_code(src, {"EXIT_X": 10, "EXIT_Y": 14}) == {9, 10, 11, 12, 13, 14}
