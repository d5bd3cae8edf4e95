"""Every switchable fault is in the recording exactly where the truth says."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.sim.detect import detect_target
from pipeline.sim.scenario import load_scenario
from pipeline.sim.simulator import write_recording

SCEN = Path(__file__).resolve().parents[1] / "datasets" / "scenarios"
ALL = {
    "capture_while_moving",
    "second_blob",
    "unconverged",
    "target_knocked",
    "joint_state_gap",
    "target_lost",
    "truncated_file",
}


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    sc = load_scenario(SCEN / "faults.toml")
    sc = dataclasses.replace(
        sc,
        poses=dataclasses.replace(sc.poses, per_target=3),
        touchup=dataclasses.replace(sc.touchup, max_iterations=8),
    )
    out = tmp_path_factory.mktemp("simf") / "faults.mcap"
    truth = write_recording(sc, 5, out)
    # read what survives of the truncated file by streaming
    js: list[tuple[int, np.ndarray, np.ndarray]] = []
    imgs: list[tuple[int, np.ndarray]] = []
    with out.open("rb") as f:
        reader = NonSeekingReader(f, decoder_factories=[DecoderFactory()])
        try:
            for _, ch, _, ros in reader.iter_decoded_messages(log_time_order=False):
                st = (
                    ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec
                    if ch.topic != "/robot_description"
                    else 0
                )
                if ch.topic == "/joint_states":
                    js.append((st, np.array(ros.position), np.array(ros.velocity)))
                elif ch.topic.startswith("/camera"):
                    im = cv2.imdecode(np.frombuffer(ros.data, np.uint8), cv2.IMREAD_UNCHANGED)
                    imgs.append((st, im))
        except Exception:  # noqa: BLE001 - the truncated tail
            pass
    return {"path": out, "truth": truth, "js": js, "imgs": imgs}


def _fault(truth: dict[str, Any], kind: str) -> dict[str, Any]:
    return next(f for f in truth["faults"] if f["type"] == kind)


def test_every_fault_listed(rec: dict[str, Any]) -> None:
    kinds = {f["type"] for f in rec["truth"]["faults"]}
    assert kinds == ALL
    for f in rec["truth"]["faults"]:
        if f["type"] != "joint_state_gap":
            assert len(f["image_indices"]) == len(f["image_log_times_ns"]) >= 1


def test_truncated_file_lacks_summary(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    tr = truth["truncated"]
    assert (
        tr["kept_bytes"] < tr["original_bytes"] == _fault(truth, "truncated_file")["original_bytes"]
    )
    assert rec["path"].stat().st_size == tr["kept_bytes"]
    with rec["path"].open("rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - a reader may also raise on the cut footer
            summary = None
    assert summary is None
    assert len(rec["imgs"]) == tr["messages_kept"][truth["image_topic"]]
    assert len(rec["js"]) == tr["messages_kept"]["/joint_states"]
    lost = _fault(truth, "truncated_file")["image_indices"]
    assert lost and min(lost) == len(rec["imgs"])
    # every other fault's images survived the cut
    for f in truth["faults"]:
        if f["type"] not in ("truncated_file", "joint_state_gap", "target_knocked"):
            assert max(f["image_indices"]) < len(rec["imgs"])


def _transition_pixels(img: np.ndarray, uv: list[float]) -> int:
    """Pixels between target and plate grey near the target: the edge width (blur) measure."""
    u, v = int(round(uv[0])), int(round(uv[1]))
    roi = img[max(v - 45, 0) : v + 46, max(u - 45, 0) : u + 46].astype(float)
    return int(np.count_nonzero((roi > 70) & (roi < 170)))


def test_capture_while_moving_is_blurred_and_arm_moves(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    f = _fault(truth, "capture_while_moving")
    i = f["image_indices"][0]
    assert truth["images"][i]["moving"] and f["blur_px"][0] > 2.0
    stills = [im for im in truth["images"] if not im["moving"] and im["touchup"] == f["touchup"]]
    still = np.median(
        [_transition_pixels(rec["imgs"][im["index"]][1], im["true_centre_px"]) for im in stills]
    )
    moving = _transition_pixels(rec["imgs"][i][1], truth["images"][i]["true_centre_px"])
    assert moving > 1.5 * still
    st = rec["imgs"][i][0]
    around = [(p, v) for s, p, v in rec["js"] if abs(s - st) <= 20_000_000]
    assert around and all(np.max(np.abs(v)) > 1e-3 for _, v in around)
    assert np.max(np.abs(around[-1][0] - around[0][0])) > 1e-4
    # every other image: joint velocities zero around the stamp
    for im in truth["images"][:20]:
        if not im["moving"]:
            near = [v for s, _, v in rec["js"] if abs(s - im["stamp_ns"]) <= 20_000_000]
            assert all(np.max(np.abs(v)) == 0.0 for v in near)


def test_joint_state_gap(rec: dict[str, Any]) -> None:
    f = _fault(rec["truth"], "joint_state_gap")
    a, b = f["missing_stamps_ns"]
    stamps = np.array([s for s, _, _ in rec["js"]])
    assert not np.any((stamps >= a) & (stamps <= b))
    i = f["last_index_before"]
    assert f["first_index_after"] == i + 1
    assert stamps[i] < a and stamps[i + 1] > b
    assert (stamps[i + 1] - stamps[i]) / 1e9 == pytest.approx(f["duration_s"] + 0.01)


def test_second_blob_in_image(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    f = _fault(truth, "second_blob")
    for i in f["image_indices"]:
        img = rec["imgs"][i][1]
        mask = (img < 105).astype(np.uint8)
        n, _, stats, _ = cv2.connectedComponentsWithStats(mask)
        big = [s for s in stats[1:] if s[cv2.CC_STAT_AREA] >= 30]
        assert len(big) == 2, i
        assert truth["images"][i]["second_blob"]


def test_lost_target_is_occluded(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    f = _fault(truth, "target_lost")
    tu = truth["touchups"][f["touchup"]]
    assert tu["lost"] and not tu["converged"]
    for i in f["image_indices"]:
        img = rec["imgs"][i][1]
        assert detect_target(img) is None
        u, v = truth["images"][i]["true_centre_px"]
        assert img[int(round(v)), int(round(u))] > 120  # the dark target is hidden


def test_unconverged_touchup(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    f = _fault(truth, "unconverged")
    tu = truth["touchups"][f["touchup"]]
    assert not tu["converged"] and not tu["lost"]
    th = float(truth["metadata"]["threshold_px"])
    e = tu["final_error_px"]
    assert max(abs(e[0]), abs(e[1])) > th or abs(e[2]) > float(
        truth["metadata"]["threshold_size_px"]
    )
    assert tu["converged_image_indices"] == []


def test_knocked_target(rec: dict[str, Any]) -> None:
    truth = rec["truth"]
    f = _fault(truth, "target_knocked")
    tg = truth["targets"][f["target"]]
    assert len(tg["history"]) == 2
    before, after = (np.asarray(h["centre"]) for h in tg["history"])
    assert np.linalg.norm(after - before) == pytest.approx(np.linalg.norm(f["shift_m"]))
    assert 1e-3 <= np.linalg.norm(after - before) <= 2e-3
    for tu in truth["touchups"]:
        if tu["target"] != f["target"] or not tu["converged"]:
            continue
        centre = np.asarray(tu["target_centre"])
        expect = after if tu["index"] in f["touchups_after"] else before
        assert np.allclose(centre, expect)
        assert np.linalg.norm(tu["pin_miss_mm"]) < 2.0


def test_faults_are_extra_attempts_and_leave_the_rest_identical(
    rec: dict[str, Any], tmp_path: Path
) -> None:
    """The same seed without faults: every touch-up of that recording is in the faulty
    one with the same converged joints and the same detections (noise drawn per plan
    pose), apart from those on the knocked target after the knock."""
    sc = load_scenario(SCEN / "faults.toml")
    no_faults = dataclasses.replace(
        sc.faults, **{f.name: False for f in dataclasses.fields(sc.faults)}
    )
    sc = dataclasses.replace(
        sc,
        poses=dataclasses.replace(sc.poses, per_target=3),
        touchup=dataclasses.replace(sc.touchup, max_iterations=8),
        faults=no_faults,
    )
    clean = write_recording(sc, 5, tmp_path / "clean.mcap")
    faulty = rec["truth"]
    knock = _fault(faulty, "target_knocked")
    per_touchup = [f for f in faulty["faults"] if "touchup" in f]
    # every fault but the knock (between touch-ups) and the truncation (one extra
    # touch-up the recorder dies in) is an extra, faulted attempt
    extra = {f["touchup"] for f in per_touchup if f["type"] != "target_knocked"}
    assert len(faulty["touchups"]) == len(clean["touchups"]) + len(extra) + 1
    after_knock = set(knock["touchups_after"])
    kept = [
        t for t in faulty["touchups"] if t["index"] not in extra and t["index"] not in after_knock
    ][: len(clean["touchups"])]
    n_same = 0
    for c in clean["touchups"]:
        match = [t for t in kept if np.array_equal(t["q"], c["q"])]
        if match:
            n_same += 1
            assert match[0]["final_error_px"] == c["final_error_px"]
            assert match[0]["target"] == c["target"]
    n_knocked = sum(1 for i in after_knock if i not in extra)
    assert n_same == len(clean["touchups"]) - n_knocked
