"""The live loop detects on the camera response ingest uses (issue 33).

An sRGB-encoded simulated cell (``small.toml`` with ``[optics] response =
"srgb"``): its ``META?`` (and the in-process ``sim:`` link) serves
``camera_response``; ``vtcal measure`` records it in the recording's
``touchup`` metadata; the loop linearises with it, so the long axis it stops
at, measured by the offline detector (``detect_target`` with the cell's
response) on the last capture of each touch-up, is within the loop's
threshold of ``s0``, whereas the loop told ``linear`` (today's loop, whatever
the cell declared) stops a few tenths of a pixel away; undeclared, it
estimates the response from its first clean captures and says so.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mcap.reader import make_reader

from pipeline.cli import main
from pipeline.sim.adapters import connect
from pipeline.sim.link import sim_cell, write_plan
from pipeline.stages.detect.detector import DetectConfig, detect_target
from pipeline.stages.ingest.stage import load_image

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def srgb_cell(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """An sRGB small cell: (sim: spec, plan of its first 3 poses: one per target)."""
    tmp = tmp_path_factory.mktemp("srgb")
    scen = tmp / "srgb.toml"
    scen.write_text(
        (REPO / "datasets" / "scenarios" / "small.toml").read_text()
        + '\n[optics]\nresponse = "srgb"\n'
    )
    spec = f"sim:{scen}:3"
    cell, _ = sim_cell(spec)
    plan = tmp / "plan.parquet"
    write_plan(cell, str(plan))
    pd.read_parquet(plan).iloc[:3].to_parquet(plan)
    return spec, plan


def _measure(
    spec: str, plan: Path, out: Path, capsys: pytest.CaptureFixture[str], *extra: str
) -> str:
    with pytest.raises(SystemExit) as e:
        main(["measure", "--plan", str(plan), "--robot", spec, "--out", str(out), "-q", *extra])
        raise SystemExit(0)
    cap = capsys.readouterr()
    assert int(e.value.code or 0) == 0, cap.err
    return cap.err


def _touchup_meta(path: Path) -> dict[str, str]:
    with path.open("rb") as f:
        for m in make_reader(f).iter_metadata():
            if m.name == "touchup":
                return dict(m.metadata)
    return {}


def _stopping_sizes(path: Path, response: str) -> np.ndarray:
    """``s - s0`` of the last capture of every touch-up, by the offline detector."""
    meta = _touchup_meta(path)
    s0 = float(meta["designated_size_px"])
    prog = json.loads(path.with_name(path.name + ".progress.json").read_text())
    ends = np.cumsum([t["captures"] for t in prog["touchups"]]) - 1
    assert all(t["converged"] for t in prog["touchups"])
    cfg = DetectConfig(polarity=meta["polarity"], response=response)
    out = []
    for k in ends:
        det = detect_target(load_image(path, "/camera/image_raw", int(k)), cfg)
        assert det["found"]
        out.append(float(det["s"]) - s0)
    return np.array(out)


def test_meta_serves_the_cells_camera_response(srgb_cell: tuple[str, Path]) -> None:
    spec, _ = srgb_cell
    link = connect(spec, None)  # in process
    try:
        assert link.metadata["camera_response"] == "srgb"
    finally:
        link.close()
    scen = spec.removeprefix("sim:").rsplit(":", 1)[0]
    cmd = [sys.executable, "-m", "pipeline", "cell-server", "--scenario", scen, "--seed", "3",
           "--port", "0"]  # fmt: skip
    for withhold, want in (((), "srgb"), (("--withhold", "camera_response"), None)):
        server = subprocess.Popen([*cmd, *withhold], stderr=subprocess.PIPE, text=True)
        try:
            assert server.stderr is not None
            tcp = connect(server.stderr.readline().split()[2], None)
            try:
                assert tcp.metadata.get("camera_response") == want
            finally:
                tcp.close()
        finally:
            server.terminate()
            server.wait()


def test_measure_records_the_response_and_the_loop_stops_where_offline_measures_it(
    srgb_cell: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec, plan = srgb_cell
    _measure(spec, plan, tmp_path / "declared.mcap", capsys)
    assert _touchup_meta(tmp_path / "declared.mcap")["camera_response"] == "srgb"
    # the loop told linear, as today's loop detected whatever the cell declared
    _measure(spec, plan, tmp_path / "linear.mcap", capsys, "--set", "camera_response=linear")
    assert _touchup_meta(tmp_path / "linear.mcap")["camera_response"] == "linear"
    declared = _stopping_sizes(tmp_path / "declared.mcap", "srgb")
    linear = _stopping_sizes(tmp_path / "linear.mcap", "srgb")
    # declared: the loop's own threshold (0.5 px) holds in the offline detector's measure
    assert np.all(np.abs(declared) <= 0.25), declared
    # the stopping size moves with the declared response (sRGB reads a dark disc short)
    assert np.mean(linear) - np.mean(declared) > 0.3, (linear, declared)


def test_an_undeclared_response_is_estimated_from_the_first_captures_and_said(
    srgb_cell: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec, plan = srgb_cell
    err = _measure(spec, plan, tmp_path / "auto.mcap", capsys, "--set", "camera_response=auto")
    assert "camera response not declared" in err and "as srgb" in err
    assert np.all(np.abs(_stopping_sizes(tmp_path / "auto.mcap", "srgb")) <= 0.5)


def test_a_bad_declared_response_is_one_line_and_nothing_is_written(
    srgb_cell: tuple[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec, plan = srgb_cell
    with pytest.raises(SystemExit) as e:
        main(["measure", "--plan", str(plan), "--robot", spec, "--out", str(tmp_path / "x.mcap"),
              "-q", "--set", "camera_response=sepia"])  # fmt: skip
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("vtcal: error: ") and "sepia" in err
    assert not (tmp_path / "x.mcap").exists()
