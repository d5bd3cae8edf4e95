"""Designated values missing from a recording, read from where its loops aimed (D1)-(D2).

A loop stops as soon as its error is inside the threshold, so the median of the
final captures sits off the designated values on the side the loops came from;
the steps themselves point at them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.stages.touchups.servo_target import loop_steps, servo_target


def _loops(rng: np.random.Generator, m0: np.ndarray, n: int = 12):
    """Seeded touch-up loops: per-loop gain, a step-length limit, a Jacobian turned
    by a degree (a loop that estimated it), 0.01 px of capture noise; each stops
    inside 0.5 px."""
    th = np.deg2rad(1.0)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1.0]])
    mk, dm, finals = [], [], []
    for _ in range(n):
        g = rng.uniform(0.3, 1.0)
        e = np.array([rng.uniform(-30, 30), rng.uniform(-30, -5), rng.uniform(-3, -0.5)])
        seen = m0 + e + 0.01 * rng.normal(size=3)
        for _ in range(40):
            if np.all(np.abs(seen - m0) < 0.5):
                break
            step = -g * (R @ e)
            if np.linalg.norm(step) > 20:
                step *= 20 / np.linalg.norm(step)
            e = e + step
            nxt = m0 + e + 0.01 * rng.normal(size=3)
            mk.append(seen)
            dm.append(nxt - seen)
            seen = nxt
        finals.append(seen)
    return np.array(mk), np.array(dm), np.array(finals)


def test_the_aim_is_read_where_the_finals_miss_it() -> None:
    rng = np.random.default_rng(3)
    m0 = np.array([319.5, 255.5, 47.77])
    mk, dm, finals = _loops(rng, m0)
    aim = servo_target(mk, dm)
    assert aim is not None
    # a turned Jacobian bends the steps' lines off the aim a little (0.03 px here)
    np.testing.assert_allclose(aim.m0, m0, atol=0.04)
    # the loops came from below in v and s: their finals stop short of the aim
    off = np.median(finals, axis=0) - m0
    assert off[1] < -0.1 and off[2] < -0.02
    assert np.all(np.abs(aim.m0 - m0)[1:] < np.abs(off[1:]) / 3)
    assert 0.3 < aim.gain <= 1.0


def test_steps_that_are_no_servo_loop_are_refused() -> None:
    rng = np.random.default_rng(4)
    assert servo_target(rng.normal(size=(5, 3)), rng.normal(size=(5, 3))) is None
    mk = rng.normal(size=(30, 3)) * 5
    assert servo_target(mk, 0.2 * mk) is None  # every step moves away from a point


def test_loop_steps_average_the_captures_at_one_pose() -> None:
    T = np.repeat(np.eye(4)[None], 5, axis=0)
    T[2:, 0, 3] = 0.01  # captures 2-4 at a second pose
    m = np.array([[0, 0, 40], [0, 0, 42], [1, 1, 45], [1, 1, 45.2], [1, 1, 45.4]], float)
    mk, dm = loop_steps([np.arange(5)], T, m, 2e-4, 2e-5)
    np.testing.assert_allclose(mk, [[0, 0, 41]])
    np.testing.assert_allclose(dm, [[1, 1, 4.2]])


def test_a_recording_without_designated_values_reads_them_from_its_loops(
    conformance_sample: Path, conformance_truth: dict, tmp_path: Path
) -> None:
    """The independent writer's sample, its designated keys removed: the loops' aim is
    within 0.05 px (centre) and 0.01 px (size) of the values it declares, where the
    median of its final captures is 0.09 px (u) and 0.038 px (size) off."""
    from pipeline.io.artefacts import read_artefact
    from pipeline.run.orchestrator import RunConfig, run_pipeline
    from pipeline.stages.ingest.types import RecordingInfo
    from pipeline.stages.touchups.stage import TouchupConfig, extract_touchups

    out = tmp_path / "run"
    run_pipeline(conformance_sample, out, RunConfig(report=False), until="touchups")
    frames = read_artefact(out / "frames.parquet", "frames")
    det = read_artefact(out / "detections.parquet", "detections")
    truth = np.array([conformance_truth["designated"][k] for k in ("u", "v", "s0")])

    def read(from_steps: bool) -> np.ndarray:
        info = RecordingInfo(**json.loads((out / "recording.json").read_text()))
        for k in ("designated_u", "designated_v", "designated_size_px"):
            info.metadata.pop(k, None)
        info.inferred["designated_u"] = "image centre"
        cfg = TouchupConfig(designated_from_steps=from_steps)
        d = extract_touchups(frames, det, info, cfg).attrs["designated"]
        assert ("loops aimed" in info.inferred["designated_size_px"]) == from_steps
        return np.array([d["u"], d["v"], d["s"]])

    aim, median = read(True), read(False)
    assert np.all(np.abs(aim[:2] - truth[:2]) < 0.05), aim - truth
    assert abs(aim[2] - truth[2]) < 0.01, aim - truth
    assert abs(median[0] - truth[0]) > 0.05 and abs(median[2] - truth[2]) > 0.02


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q", "-n", "0"])
