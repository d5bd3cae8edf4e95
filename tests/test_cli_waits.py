"""What a user sees while waiting and when a command fails early (issue 35).

`vtcal simulate` (55 s on the standard cell) and `vtcal identify` on a large table (78 s)
printed nothing after their first line; a manifest's simulated recordings had to be
made by hand from comments; `run` and `validate` printed a blank line before an error
and left an empty run folder for a rejected file; four commands had no example in
their ``--help``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from pipeline.cli import cli

REPO = Path(__file__).resolve().parent.parent
SMALL = REPO / "datasets" / "scenarios" / "small.toml"


@pytest.fixture(scope="module")
def small_rec(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("sim") / "small.mcap"
    res = CliRunner().invoke(cli, ["simulate", "--scenario", str(SMALL), "--seed", "3", "--out",
                                   str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    return out, res.output


def test_simulate_shows_its_progress(small_rec: tuple[Path, str]) -> None:
    out, text = small_rec
    bar = next((line for line in text.splitlines() if line.startswith("touch-ups")), None)
    assert bar is not None, text
    assert "6/6" in bar  # 3 targets x 2 poses, every attempt counted


def test_identify_shows_a_bar_per_stage(lrmate_run: Path, tmp_path: Path) -> None:
    table, urdf = lrmate_run.parent / "table.csv", lrmate_run.parent / "nominal.urdf"
    res = CliRunner().invoke(cli, ["identify", str(table), "--urdf", str(urdf), "--out",
                                   str(tmp_path / "id"), "--no-report"])  # fmt: skip
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    for stage in ("identify", "crossval", "choose"):
        assert any(line.startswith(stage) and "1/1" in line for line in lines), (stage, lines)


def test_a_manifest_simulates_its_missing_recordings(tmp_path: Path) -> None:
    """The fleet demo's recordings are made by the batch itself (``simulate`` key)."""
    from pipeline.batch.run import load_manifest, run_batch

    m = tmp_path / "m.toml"
    m.write_text(
        f'[[recordings]]\npath = "made/small.mcap"\n'
        f'simulate = {{ scenario = "{SMALL}", seed = 3 }}\n'
    )
    items = load_manifest(m).items
    assert items[0].simulate == (str(SMALL), 3)
    res = run_batch(items, tmp_path / "out", workers=1, until="ingest")
    assert [o.status for o in res.outcomes] == ["ok"], res.outcomes[0].error
    assert (tmp_path / "made" / "small.mcap").is_file()
    assert (tmp_path / "made" / "small.mcap.truth.json").is_file()


def test_the_shipped_fleet_manifest_says_how_to_make_every_recording() -> None:
    from pipeline.batch.run import load_manifest

    for it in load_manifest(REPO / "datasets" / "fleet_demo.toml").items:
        assert it.recording.exists() or it.simulate is not None, it.name


def test_a_bad_simulate_entry_is_one_line(tmp_path: Path) -> None:
    from pipeline.batch.run import load_manifest
    from pipeline.errors import BadInput

    m = tmp_path / "m.toml"
    m.write_text('[[recordings]]\npath = "x.mcap"\nsimulate = { scenario = "nope.toml" }\n')
    with pytest.raises(BadInput, match=r"recordings\[0\]: 'simulate' must be"):
        load_manifest(m)


@pytest.mark.parametrize("command", ["run", "validate"])
def test_a_rejected_file_prints_one_line_and_leaves_no_folder(command: str, tmp_path: Path):
    import subprocess
    import sys

    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"junk\n")
    out = tmp_path / "out"
    urdf = REPO / "pipeline" / "robots" / "lrmate.urdf"
    args = ["run", str(junk)] if command == "run" else ["validate", str(urdf), str(junk)]
    proc = subprocess.run([sys.executable, "-m", "pipeline", *args, "--out", str(out)],
                          capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    # nothing but what a progress display said (a first run's detector compilation)
    assert all(line.strip() for line in proc.stdout.splitlines()), repr(proc.stdout)
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("vtcal: error: ")
    assert not out.exists()


@pytest.mark.parametrize(
    "command", ["run", "simulate", "identify", "report", "validate", "compare", "plan",
                "measure", "calibrate", "cell-server", "export", "batch"],
)  # fmt: skip
def test_every_help_has_an_example(command: str) -> None:
    res = CliRunner().invoke(cli, [command, "--help"])
    assert res.exit_code == 0
    text = res.output
    assert "Examples:" in text, command
    examples = text[text.index("Examples:") :].splitlines()[1:]
    assert any(line.strip().startswith(f"vtcal {command} ") for line in examples), text
