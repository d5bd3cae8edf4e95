"""vtcal measure end to end on the simulated cell: over TCP (a real socket) and in process,
killed and resumed, and the cell-side faults (one line, exit 4, the recording kept)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from pipeline.cli import main
from pipeline.io import mcap as io_mcap
from pipeline.live.protocols import MeasureFault
from pipeline.live.record import read_progress
from pipeline.live.summary import from_metadata
from pipeline.live.tcp_server import Cell, CellServer, serve_in_thread
from pipeline.sim.link import sim_cell, write_plan

REPO = Path(__file__).resolve().parent.parent
SCENARIO = REPO / "datasets" / "scenarios" / "small.toml"
SIM = f"sim:{SCENARIO}:1"


def _vtcal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main([*argv])
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(e.value.code or 0), out.out, out.err


def _plan(tmp: Path, n: int | None = None) -> Path:
    cell, _ = sim_cell(SIM)
    path = tmp / "plan.parquet"
    write_plan(cell, str(path))
    if n is not None:
        pd.read_parquet(path).iloc[:n].to_parquet(path)
    return path


def _serve(wrap: Any = None) -> CellServer:
    cell, tap = sim_cell(SIM)
    robot, camera = (cell.robot, cell.camera) if wrap is None else wrap(cell.robot, cell.camera)
    return serve_in_thread(Cell(robot, camera, tap.since, cell.nominal_urdf, cell.served_metadata))


def _images(path: Path) -> tuple[bool, int, int]:
    state = io_mcap.StreamState(str(path))
    n_img = n_joint = 0
    for m in io_mcap.iter_messages(path, state):
        topic = state.topic_type(m.channel_id)[0]
        n_img += topic == "/camera/image_raw"
        n_joint += topic == "/joint_states"
    return state.truncated, n_img, n_joint


def test_tcp_and_in_process_measure_the_same_and_vtcal_run_calibrates_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = _plan(tmp_path)
    server = _serve()
    try:
        url = f"tcp://127.0.0.1:{server.port}"
        code, out, err = _vtcal(
            [
                "measure",
                "--plan",
                str(plan),
                "--robot",
                url,
                "--out",
                str(tmp_path / "tcp.mcap"),
                "-q",
            ],
            capsys,
        )
    finally:
        server.shutdown()
        server.server_close()
    assert code == 0, err
    assert "6/6 touch-ups: 6 converged" in out
    code, out, err = _vtcal(
        ["measure", "--plan", str(plan), "--robot", SIM, "--out", str(tmp_path / "sim.mcap"), "-q"],
        capsys,
    )
    assert code == 0, err
    # the protocol carries floats and pixels exactly: the same cell gives the same file
    assert (tmp_path / "tcp.mcap").read_bytes() == (tmp_path / "sim.mcap").read_bytes()
    truncated, n_img, n_joint = _images(tmp_path / "tcp.mcap")
    assert not truncated and n_img == 45  # 6 x (2 loop + 2 extra) + 3 targets x 7 probes
    assert n_joint >= 50 * 50  # >= 50 Hz over the ~57 s of cell time
    code, out, err = _vtcal(
        ["run", str(tmp_path / "tcp.mcap"), "--out", str(tmp_path / "run"), "-q", "--no-report"],
        capsys,
    )
    assert code in (0, 3), err  # 3: a 6-pose cell may not improve on the nominal robot
    tu = pd.read_parquet(tmp_path / "run" / "touchups.parquet")
    assert len(tu) == 6
    # the recording says how it was measured; ingest keeps it for the report
    info = json.loads((tmp_path / "run" / "recording.json").read_text())
    m = from_metadata(info["measurement"])
    assert (m["n_plan"], m["converged"], m["captures"], m["gave_up"]) == (6, 6, 45, {})
    assert 40.0 < m["cell_s"] < 80.0 and m["sessions"] == 1
    prog = read_progress(tmp_path / "tcp.mcap")
    assert prog is not None and prog.finished and prog.done == 6


def _wait_progress(path: Path, done: int, proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        p = read_progress(path) if path.with_name(path.name + ".progress.json").exists() else None
        if p is not None and p.done >= done:
            return
        if proc.poll() is not None:
            raise AssertionError(
                f"vtcal measure ended early: {proc.stderr.read() if proc.stderr else ''}"
            )
        time.sleep(0.02)
    raise AssertionError("vtcal measure made no progress")


def test_a_killed_measure_leaves_a_readable_recording_that_resumes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = _plan(tmp_path)
    out = tmp_path / "rec.mcap"
    argv = ["measure", "--plan", str(plan), "--robot", SIM, "--out", str(out), "-q"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline", *argv], env=env, stderr=subprocess.PIPE
    )
    try:
        _wait_progress(out, 2, proc, 120.0)
        time.sleep(0.3)  # into touch-up 3
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = read_progress(out).done  # type: ignore[union-attr]
    assert 2 <= done < 6
    truncated, n_img, _ = _images(out)
    assert truncated and n_img >= 9 * done // 2  # every capture of the finished touch-ups
    code, _, err = _vtcal(
        ["run", str(out), "--out", str(tmp_path / "partial"), "--until", "touchups", "-q"], capsys
    )
    assert code == 0 and "truncated recording" in err
    assert len(pd.read_parquet(tmp_path / "partial" / "touchups.parquet")) >= done

    code, stdout, err = _vtcal(argv, capsys)
    assert code == 0, err
    assert "6/6 touch-ups: 6 converged" in stdout and "over 2 sessions" in stdout
    truncated, _, _ = _images(out)
    assert not truncated
    code, _, err = _vtcal(
        ["run", str(out), "--out", str(tmp_path / "full"), "--until", "touchups", "-q"], capsys
    )
    assert code == 0, err
    tu = pd.read_parquet(tmp_path / "full" / "touchups.parquet")
    assert len(tu) == 6
    m = from_metadata(json.loads((tmp_path / "full" / "recording.json").read_text())["measurement"])
    assert m["converged"] == 6 and m["sessions"] == 2


class _Faulty:
    """Delegates to a simulated robot or camera; raises ``exc`` on the ``at``-th call of ``method``."""

    def __init__(self, inner: Any, method: str, at: int, exc: BaseException) -> None:
        self._inner, self._method, self._at, self._exc, self._n = inner, method, at, exc, 0

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._inner, name)
        if name != self._method:
            return attr

        def call(*a: Any) -> Any:
            self._n += 1
            if self._n == self._at:
                raise self._exc
            return attr(*a)

        return call

    @property
    def joint_names(self) -> list[str]:
        return list(self._inner.joint_names)


@pytest.mark.parametrize(
    ("side", "method", "at", "exc", "kind"),
    [
        ("robot", "move_flange", 20, RuntimeError("controller program crashed"), "connection"),
        (
            "robot",
            "move_joints",
            3,
            MeasureFault("move_refused", "protective stop"),
            "move_refused",
        ),
        (
            "camera",
            "capture",
            25,
            MeasureFault("camera_timeout", "no image in 2 s"),
            "camera_timeout",
        ),
    ],
)
def test_cell_faults_give_one_line_exit_4_and_keep_the_recording(
    side: str, method: str, at: int, exc: BaseException, kind: str, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    plan = _plan(tmp_path)

    def wrap(robot: Any, camera: Any) -> tuple[Any, Any]:
        if side == "robot":
            return _Faulty(robot, method, at, exc), camera
        return robot, _Faulty(camera, method, at, exc)

    server = _serve(wrap)
    out = tmp_path / "rec.mcap"
    try:
        url = f"tcp://127.0.0.1:{server.port}"
        code, _, err = _vtcal(
            ["measure", "--plan", str(plan), "--robot", url, "--out", str(out), "-q"], capsys
        )
    finally:
        server.shutdown()
        server.server_close()
    # the in-test server's own line (it says why it dropped the link) is not vtcal measure's
    lines = [x for x in err.strip().splitlines() if not x.startswith("vtcal cell-server:")]
    assert code == 4 and len(lines) == 1, err
    assert f": {kind}: " in lines[0] and "recording so far is kept" in lines[0]
    prog = read_progress(out)
    assert prog is not None and not prog.finished and 1 <= prog.done < 6
    truncated, n_img, _ = _images(out)
    assert n_img >= sum(t["captures"] for t in prog.touchups)


class _Blind:
    """A camera that sees only the plate (the target is gone)."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner

    def capture(self) -> Any:
        from pipeline.live.protocols import Frame

        f = self._inner.capture()
        return Frame(np.full_like(f.image, 200), f.stamp_ns, f.encoding)


def test_three_touchups_without_the_target_stop_with_target_not_found(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = _plan(tmp_path)
    server = _serve(lambda robot, camera: (robot, _Blind(camera)))
    out = tmp_path / "rec.mcap"
    try:
        url = f"tcp://127.0.0.1:{server.port}"
        code, _, err = _vtcal(
            ["measure", "--plan", str(plan), "--robot", url, "--out", str(out), "-q"], capsys
        )
    finally:
        server.shutdown()
        server.server_close()
    lines = err.strip().splitlines()
    assert code == 4 and len(lines) == 1, err
    assert ": target_not_found: touch-ups 1..3:" in lines[0]
    prog = read_progress(out)
    assert prog is not None and prog.done == 3
    assert [t["reason"] for t in prog.touchups] == ["no_jacobian"] * 3


def test_calibrate_measures_once_and_reports_the_measurement(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = _plan(tmp_path)
    argv = ["calibrate", "--robot", SIM, "--plan", str(plan), "--out", str(tmp_path / "cal"), "-q"]
    code, out, err = _vtcal(argv, capsys)
    assert code in (0, 3), err  # 3: NOT improved is possible on 6 poses
    m = json.loads((tmp_path / "cal" / "measure.json").read_text())
    assert m["converged"] == 6 and m["captures"] == 45 and m["cell_s"] > 10
    assert out.count("measured 6/6 touch-ups: 6 converged") == 2  # after measuring and at the end
    assert (tmp_path / "cal" / "run" / "calibrated.urdf").exists()
    # the report says how the recording was measured (from the recording itself)
    html = (tmp_path / "cal" / "run" / "report.html").read_text()
    assert "by vtcal measure: 6 of 6 planned touch-ups converged; 45 captures" in html
    stamp = (tmp_path / "cal" / "recording.mcap").stat().st_mtime_ns
    code2, out2, _ = _vtcal(argv, capsys)
    assert code2 == code and "measured 6/6" in out2
    assert (tmp_path / "cal" / "recording.mcap").stat().st_mtime_ns == stamp  # not re-measured
