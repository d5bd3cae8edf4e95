"""Field recordings as they come (issue 34): each variant read right or refused in one line.

Every variant is written as a recorder would write it: a small simulated
recording is copied message by message (``support.field_variants.rewrite``)
with the one difference, and the CLI runs on it in-process. Every URDF, JSON
and Parquet file a run writes must parse; a refusal must leave one
``vtcal: error:`` line on stderr and nothing partial in ``--out``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.field_variants import rewrite, simulated, written_files_parse
from test_robustness_data import run_cli


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    return simulated(tmp_path_factory.mktemp("field"))


def _run(rec: Path, out: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    return run_cli(["run", str(rec), "--out", str(out), "-q", "--no-report", *extra], capsys)


def _one_error(code: int, err: list[str], want: int, *needles: str) -> str:
    assert code == want, err
    assert len(err) == 1, err
    assert err[0].startswith("vtcal: error: "), err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]


# --------------------------------------------------------------- 1: URDF with a BOM


def test_urdf_with_byte_order_mark_is_read_and_written_well_formed(sim, tmp_path, capsys):
    rec, _ = sim

    def bom(topic: str, msg: dict) -> dict:
        if topic == "/robot_description":
            msg["data"] = "\ufeff" + msg["data"]
        return msg

    variant = rewrite(rec, tmp_path / "bom.mcap", bom)
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys)
    assert code == 0, err
    written = written_files_parse(out)
    assert "calibrated.urdf" in written and "recording.json" in written
    urdf = json.loads((out / "recording.json").read_text())["urdf"]
    assert not urdf.startswith("\ufeff")
