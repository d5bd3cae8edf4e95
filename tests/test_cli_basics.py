"""CLI plumbing: help everywhere, one-line errors with exit codes, known-distance parsing."""

from __future__ import annotations

import subprocess
import sys

import pytest
from click.testing import CliRunner

from pipeline.cli import COMMANDS, cli, main
from pipeline.errors import BadInput
from pipeline.io.known_distances import parse_distances


def test_help_lists_every_declared_command() -> None:
    res = CliRunner().invoke(cli, ["--help"])
    assert res.exit_code == 0
    # every command declared in cli.COMMANDS has its module (none hidden as "not built")
    assert sorted(cli.list_commands(None)) == sorted(COMMANDS)  # type: ignore[arg-type]
    listed = [ln.split()[0] for ln in res.output.split("Commands:")[1].splitlines() if ln.strip()]
    assert sorted(listed) == sorted(COMMANDS)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_has_help(name: str) -> None:
    res = CliRunner().invoke(cli, [name, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage: " in res.output and len(res.output.splitlines()) > 4


@pytest.mark.parametrize("module", ["pipeline", "pipeline.cli"])
def test_module_entry_point_runs(module: str) -> None:
    out = subprocess.run(
        [sys.executable, "-m", module, "--version"], capture_output=True, text=True, check=True
    )
    assert "vtcal" in out.stdout


def test_vtcal_error_is_one_line_with_exit_code(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["run", "/nonexistent/rec.mcap", "--out", "/tmp/vtcal-never", "-q"])
    assert exc.value.code == BadInput.exit_code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/nonexistent/rec.mcap" in err[0]


def test_parse_distances() -> None:
    assert parse_distances("0:2=0.725946") == [(0, 2, 0.725946)]
    assert parse_distances("a:b=1; 0:1=0.5") == [("a", "b", 1.0), (0, 1, 0.5)]
    assert parse_distances("") == []
    for bad in ("0:2", "0=1", "0:2=-1", "0:2=x", ":2=1"):
        with pytest.raises(BadInput, match="expected A:B=METRES"):
            parse_distances(bad)


def test_interrupt_inside_an_import_counts_as_an_interrupt() -> None:
    from pipeline.cli import _caused_by_interrupt

    def import_interrupted() -> None:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None

    try:
        import_interrupted()
    except ImportError as exc:
        assert _caused_by_interrupt(exc)  # context kept even with 'from None'
    try:
        raise ValueError("a bug")
    except ValueError as exc:
        assert not _caused_by_interrupt(exc)


def test_model_auto_ships_under_the_model_it_fitted(tmp_path) -> None:
    """``--model auto`` said 'calibrated.urdf from model auto'; it names what auto fitted."""
    import json

    from test_identify import _case

    urdf, _, _, table, _ = _case(seed=4, per_target=10, noise_pin=10e-6)
    table.to_csv(tmp_path / "t.csv", index=False)
    (tmp_path / "r.urdf").write_text(urdf)
    res = CliRunner().invoke(
        cli,
        ["identify", str(tmp_path / "t.csv"), "--urdf", str(tmp_path / "r.urdf"),
         "--out", str(tmp_path / "o"), "--model", "auto", "--no-report"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "o" / "identify.json").read_text())
    assert summary["best_model"] == summary["model"] == "full"
    assert "calibrated.urdf from model full" in res.output
    assert "from model auto" not in res.output
    assert "auto (which fitted full)" in res.output


def test_a_truncation_warning_is_shown_when_the_run_then_fails(tmp_path) -> None:
    """A truncated recording that leaves too few touch-ups: exit 3, one line that says why."""
    from pathlib import Path

    sample = Path(__file__).resolve().parents[1] / "datasets" / "samples" / "sample_lrmate.mcap"
    data = sample.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.35)])
    r = subprocess.run(
        [sys.executable, "-m", "pipeline", "run", str(cut), "--out", str(tmp_path / "o"), "-q",
         "--no-report"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 3, r.stderr
    lines = r.stderr.strip().splitlines()
    # still one line: the warning rides in the error line
    assert len(lines) == 1 and lines[0].startswith("vtcal: error:"), lines
    assert "ingest warned:" in lines[0] and "truncated recording" in lines[0], lines


@pytest.mark.parametrize("command", ["identify", "plan"])
def test_model_help_lists_every_registered_model(command: str) -> None:
    from pipeline.models import model_names

    res = CliRunner().invoke(cli, [command, "--help"], terminal_width=400)
    assert res.exit_code == 0
    assert all(name in res.output for name in model_names()), res.output
