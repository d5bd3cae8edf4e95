"""The simulated recording follows the spec and its truth is right (small scenario)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.kinematics import fk, load_chain
from pipeline.kinematics.se3 import invert_transform
from pipeline.sim.scenario import load_scenario
from pipeline.sim.simulator import write_recording

ROOT = Path(__file__).resolve().parents[1]
SCEN = ROOT / "datasets" / "scenarios"
CHECKER = Path("/work/shared/tools/check_recording.py")


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("sim") / "small.mcap"
    truth = write_recording(load_scenario(SCEN / "small.toml"), 7, out)
    return out, truth


def _messages(path: Path, topics: list[str] | None = None) -> list[tuple[str, Any, Any]]:
    with path.open("rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, m, ros) for _, c, m, ros in r.iter_decoded_messages(topics=topics)]


def test_container_topics_types_metadata(small: tuple[Path, dict[str, Any]]) -> None:
    path, truth = small
    with path.open("rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        assert r.get_header().profile == "ros2"
        s = r.get_summary()
        assert s is not None
        chans = {c.topic: c for c in s.channels.values()}
        types = {t: s.schemas[c.schema_id].name for t, c in chans.items()}
        assert types == {
            "/robot_description": "std_msgs/msg/String",
            "/joint_states": "sensor_msgs/msg/JointState",
            "/camera/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
        }
        assert all(c.message_encoding == "cdr" for c in chans.values())
        assert all(sc.encoding == "ros2msg" for sc in s.schemas.values())
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    md = meta["touchup"]
    for key in (
        "base_link", "flange_link", "target_diameter_m", "designated_u", "designated_v",
        "designated_size_px", "threshold_px", "threshold_size_px", "polarity", "known_distances",
    ):  # fmt: skip
        assert key in md
    assert md == truth["metadata"]
    assert float(md["designated_size_px"]) == pytest.approx(truth["designated"]["s0"])
    assert md["known_distances"].startswith("0:2=")


def test_stream_content(small: tuple[Path, dict[str, Any]]) -> None:
    path, truth = small
    msgs = _messages(path)
    assert msgs[0][0] == "/robot_description"
    assert "<robot" in msgs[0][2].data and truth["nominal_urdf"] == msgs[0][2].data
    log_times = [m.log_time for _, m, _ in msgs]
    assert log_times == sorted(log_times)
    assert [m.sequence for _, m, _ in msgs] == list(range(len(msgs)))
    js = [(m, ros) for t, m, ros in msgs if t == "/joint_states"]
    stamps = np.array([ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec for _, ros in js])
    assert np.median(np.diff(stamps)) == pytest.approx(1e7)  # 100 Hz
    assert np.max(np.diff(stamps)) <= 1e7  # no gap without the fault
    assert all(list(ros.name) == truth["joint_names"] for _, ros in js[:10])
    imgs = [(m, ros) for t, m, ros in msgs if t.startswith("/camera")]
    assert len(imgs) == truth["counts"]["images"] == len(truth["images"])
    assert len(js) == truth["counts"]["joint_states"]
    for (m, ros), rec in zip(imgs, truth["images"], strict=True):
        assert m.log_time == rec["log_time_ns"] and m.sequence == rec["mcap_sequence"]
        st = ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec
        assert st == rec["stamp_ns"] < rec["log_time_ns"]
    img = cv2.imdecode(np.frombuffer(imgs[0][1].data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (512, 640) and img.dtype == np.uint8


def test_still_at_captures_and_encoder_noise(small: tuple[Path, dict[str, Any]]) -> None:
    path, truth = small
    js = _messages(path, ["/joint_states"])
    stamps = np.array([ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec for _, _, ros in js])
    pos = np.array([list(ros.position) for _, _, ros in js])
    for rec in truth["images"]:
        near = np.abs(stamps - rec["stamp_ns"]) <= 30_000_000
        assert near.sum() >= 5
        dev = pos[near] - np.asarray(rec["q_true"])
        assert np.max(np.abs(dev)) < 1e-5  # still: only encoder noise (1e-6 rad)
    # encoder noise is there, at the stated level
    d = np.diff(pos[:50], axis=0)
    assert 0.5e-6 < np.std(d) / np.sqrt(2) < 2e-6


def test_true_pin_touches_true_target(small: tuple[Path, dict[str, Any]]) -> None:
    _, truth = small
    chain = load_chain(truth["true_urdf_with_pin"], truth["base_link"], "virtual_pin")
    tol_lat = 0.25e-3
    s0 = truth["designated"]["s0"]
    depth_tol = truth["standoff_m"] * float(truth["metadata"]["threshold_size_px"]) / s0 + 0.2e-3
    n = 0
    for tu in truth["touchups"]:
        if not tu["converged"]:
            continue
        n += 1
        T = fk(chain, np.asarray(tu["q"]))
        miss = T[:3, 3] - np.asarray(tu["target_centre"])
        assert miss * 1000 == pytest.approx(np.asarray(tu["pin_miss_mm"]), abs=1e-9)
        # split into lateral / depth along the camera axis
        T_cam = fk(load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"]),
                   np.asarray(tu["q"])) @ np.asarray(truth["camera"]["T_flange_camera"])  # fmt: skip
        axis = T_cam[:3, 2]
        depth = float(miss @ axis)
        lateral = float(np.linalg.norm(miss - depth * axis))
        assert lateral < tol_lat, (tu["index"], lateral)
        assert abs(depth) < depth_tol, (tu["index"], depth)
    assert n == len(truth["touchups"])


def test_long_axis_follows_f_D_over_d_in_recording(small: tuple[Path, dict[str, Any]]) -> None:
    _, truth = small
    chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    T_fc = np.asarray(truth["camera"]["T_flange_camera"])
    f = truth["camera"]["fx"]
    for rec in truth["images"]:
        tg = truth["targets"][rec["target"]]
        T_cam = fk(chain, np.asarray(rec["q_true"])) @ T_fc
        p = (
            invert_transform(T_cam)[:3, :3] @ np.asarray(tg["centre"])
            + invert_transform(T_cam)[:3, 3]
        )
        s = rec["true_ellipse"][2]
        assert s == pytest.approx(f * tg["diameter_m"] / p[2], rel=0.015)
        # and the controller's own detection agrees with the true ellipse
        det = rec["sim_detection"]
        assert abs(det[0] - rec["true_ellipse"][0]) < 0.1
        assert abs(det[1] - rec["true_ellipse"][1]) < 0.1
        assert abs(det[2] - s) < 0.15


def test_truth_layout_matches_conformance_sample(small: tuple[Path, dict[str, Any]]) -> None:
    _, truth = small
    sample = Path("/work/shared/samples/conformance_lrmate_small.mcap.truth.json")
    if not sample.exists():
        pytest.skip("conformance sample not available")
    ref = json.loads(sample.read_text())
    missing = set(ref) - set(truth)
    assert not missing
    for key in ("touchups", "images", "probes", "targets"):
        assert set(ref[key][0]) <= set(truth[key][0]), key
    assert set(ref["camera"]) <= set(truth["camera"])
    assert set(next(iter(ref["deviations"].values()))) == set(
        next(iter(truth["deviations"].values()))
    )
    assert "true_ellipse" in truth["images"][0]


@pytest.mark.skipif(not CHECKER.exists(), reason="shared checker not available")
def test_check_recording_passes(small: tuple[Path, dict[str, Any]]) -> None:
    path, _ = small
    r = subprocess.run([sys.executable, str(CHECKER), str(path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.startswith("recording ok")


def test_same_seed_same_bytes(tmp_path: Path) -> None:
    sc = load_scenario(SCEN / "small.toml")
    sc = dataclasses.replace(
        sc,
        targets=dataclasses.replace(sc.targets, count=2),
        poses=dataclasses.replace(sc.poses, per_target=1),
        camera=dataclasses.replace(sc.camera, image="raw"),
    )
    a, b, c = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    write_recording(sc, 11, a)
    write_recording(sc, 11, b)
    write_recording(sc, 12, c)
    assert a.read_bytes() == b.read_bytes()
    assert Path(str(a) + ".truth.json").read_bytes() == Path(str(b) + ".truth.json").read_bytes()
    assert a.read_bytes() != c.read_bytes()
    msgs = _messages(a, ["/camera/image_raw"])
    ros = msgs[0][2]
    assert (ros.encoding, ros.height, ros.width, ros.step) == ("mono8", 512, 640, 640)
