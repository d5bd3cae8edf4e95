"""A built wheel carries what ``vtcal run`` reads besides the code: schemas, report templates,
robots, and the file contracts its help points to (``spec/``).

They live at the top of the repository (``schemas/``, ``reports/``, ``spec/``); ``setup.py``
maps them into the wheel as ``pipeline/_data/...`` and :mod:`pipeline.io.resources`
finds them there when no checkout is beside the package. Before, a plain
``pip install .`` failed at the first artefact ("no schema declared").
"""

from __future__ import annotations

import os
import runpy
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def test_the_wheel_carries_schemas_templates_and_robots(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp_path), str(REPO)],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "VTCAL_NO_PRECOMPILE": "1"},  # the compile: test below
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = tmp_path.glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for folder, inside in (
        ("schemas", "pipeline/_data/schemas"),
        ("reports", "pipeline/_data/reports"),
        ("spec", "pipeline/_data/spec"),  # the contracts `vtcal run --help` points to
    ):
        for f in (REPO / folder).rglob("*"):
            if f.is_file():
                assert f"{inside}/{f.relative_to(REPO / folder).as_posix()}" in names, f
    assert {f"pipeline/robots/{p.name}" for p in (REPO / "pipeline/robots").glob("*.urdf")} <= names
    assert not any(n.startswith(("tests/", "benchmarks/", "datasets/")) for n in names)


def test_the_contracts_ship_and_the_helps_point_to_them() -> None:
    """``spec/`` holds the three contracts, and no help text, docstring or doc points to
    ``shared/spec/`` (a folder neither the repository nor the package has)."""
    from pipeline.io import resources

    assert {p.name for p in resources.data_dir("spec").glob("*.md")} == {
        "recording.md", "touchups.md", "outputs.md",
    }  # fmt: skip
    stale = [
        f"{p.relative_to(REPO)}:{i}"
        for p in [*sorted((REPO / "pipeline").rglob("*.py")), *sorted((REPO / "docs").glob("*.md"))]
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if "shared/spec" in line
    ]
    assert not stale, f"points to shared/spec/ instead of spec/: {stale}"
    from click.testing import CliRunner

    from pipeline.cli import cli

    out = CliRunner().invoke(cli, ["run", "--help"], terminal_width=200).output
    assert "spec/recording.md" in out and "shared/spec" not in out


def test_resources_fall_back_to_the_wheels_copy(tmp_path: Path, monkeypatch) -> None:
    from pipeline.io import resources

    assert resources.data_dir("schemas") == REPO / "schemas"
    fake_pkg = tmp_path / "site" / "pipeline"
    (fake_pkg / "_data" / "schemas").mkdir(parents=True)
    monkeypatch.setattr(resources, "PACKAGE_DIR", fake_pkg)
    assert resources.data_dir("schemas") == fake_pkg / "_data" / "schemas"


@pytest.fixture
def build_command(monkeypatch):
    """setup.py's build_py command (``setup()`` not run) and the subprocess calls it makes."""
    import setuptools
    from setuptools.command.build_py import build_py
    from setuptools.dist import Distribution

    monkeypatch.setattr(setuptools, "setup", lambda **kw: None)
    ns = runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    calls: list[tuple[list[str], dict[str, str]]] = []

    def fake_run(args, env, **kw):
        calls.append((list(args), dict(env)))
        return subprocess.CompletedProcess(args, 0, stdout="12.3\n", stderr="")

    monkeypatch.setattr(build_py, "run", lambda self: None)  # the copying itself
    monkeypatch.setattr(ns["subprocess"], "run", fake_run)
    return ns["BuildWithDetector"](Distribution()), calls


def test_the_build_compiles_the_detector_into_the_built_tree(build_command, tmp_path, monkeypatch):
    """The wheel's numba cache is made from the built tree's own stages/detect/_jit.py."""
    cmd, calls = build_command
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    monkeypatch.delenv("VTCAL_NO_PRECOMPILE", raising=False)
    cmd.build_lib = str(tmp_path / "build" / "lib")
    cmd.run()
    ((args, env),) = calls
    assert args[0] == sys.executable and args[-1] == cmd.build_lib
    assert "compile_detector" in args[2] and "NUMBA_CACHE_DIR" not in env  # into the tree


def test_an_editable_install_compiles_into_the_checkout_and_keeps_its_cache(
    build_command, tmp_path, monkeypatch
):
    """The README's set-up line is an editable install: it imports the checkout, so the
    detector is compiled there (not into the throw-away build tree), and the checkout's
    numba cache stays (numba reuses it when it is current)."""
    cmd, calls = build_command
    monkeypatch.delenv("VTCAL_NO_PRECOMPILE", raising=False)
    cmd.build_lib = str(tmp_path)
    stale = tmp_path / "pipeline" / "stages" / "detect" / "__pycache__" / "_jit.x-1.py311.nbi"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"an earlier build's")
    cmd.editable_mode = True
    cmd.run()
    ((args, env),) = calls
    assert args[-1] == str(REPO) and args[-1] != cmd.build_lib
    assert "compile_detector" in args[2] and "NUMBA_CACHE_DIR" not in env
    assert stale.exists()


@pytest.mark.parametrize("how", ["editable", "env"])
def test_no_compile_when_asked(build_command, tmp_path, monkeypatch, how):
    cmd, calls = build_command
    cmd.build_lib = str(tmp_path)
    stages = tmp_path / "pipeline" / "stages"
    stale = stages / "detect" / "__pycache__" / "_jit.fine_stage-1.py311.nbi"
    stale_fit = stages / "response" / "__pycache__" / "_edge_jit.edge_residual_jacobian-1.py311.nbc"
    for f in (stale, stale_fit):
        f.parent.mkdir(parents=True)
        f.write_bytes(b"an earlier build's")
    if how == "editable":
        cmd.editable_mode = True
    monkeypatch.setenv("VTCAL_NO_PRECOMPILE", "1")
    cmd.run()
    assert calls == []
    # asked not to: an earlier build's cache in the build tree is not shipped either
    assert stale.exists() == stale_fit.exists() == (how == "editable")
