"""ROS bags as recorders write them: bags written by ``rosbags``' own writers calibrate
to the same figures as the MCAP they were converted from; joint-state quirks; image
topic choice.

The bags are written with rosbags (rosbag2 MCAP / sqlite3 writers, ROS 1
writer; tests/support/rosbag_writers.py), independent of vtcal's MCAP writer and of
vtcal's readers.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from support.rosbag_writers import (
    ROS2,
    SAMPLE,
    STRING,
    Msg,
    StoragePlugin,
    sample_messages,
    with_touchup_topic,
    write_ros1_bag,
    write_rosbag2,
    write_split_mcap_bag,
)

from pipeline.cli import main
from pipeline.errors import BadInput
from pipeline.io.artefacts import read_artefact
from pipeline.io.recording import TOUCHUP_TOPIC
from pipeline.run.orchestrator import RunConfig, run_pipeline
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The shipped sample MCAP and three kinds of bag converted from it."""
    d = tmp_path_factory.mktemp("bags")
    msgs, meta = sample_messages()
    bag_msgs = with_touchup_topic(msgs, meta)
    return {
        "mcap": SAMPLE,
        "split": write_split_mcap_bag(d / "split", bag_msgs, 3),
        "db3": write_rosbag2(d / "db3bag", bag_msgs, StoragePlugin.SQLITE3),
        "ros1": write_ros1_bag(d / "rec.bag", bag_msgs),
        "zstd-file": write_rosbag2(d / "zfile", bag_msgs, StoragePlugin.MCAP, "file"),
        "zstd-message": write_rosbag2(d / "zmsg", bag_msgs, StoragePlugin.MCAP, "message"),
    }


@pytest.fixture(scope="module")
def runs(recordings: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("runs")
    cfg = RunConfig(report=False, stage_options={"identify": {"model": "offsets"}})
    for name, rec in recordings.items():
        run_pipeline(rec, out / name, cfg, until="identify")
    return {name: out / name for name in recordings}


def test_split_bag_layout(recordings: dict[str, Path]) -> None:
    """The split bag really is three .mcap files read in metadata.yaml's order."""
    from pipeline.io.layout import locate

    lay = locate(recordings["split"])
    assert lay.kind == "rosbag2-mcap" and [f.name for f in lay.files] == [
        f"split_{i}.mcap" for i in range(3)
    ]
    assert locate(recordings["db3"]).kind == "rosbag2-sqlite3"
    assert locate(recordings["ros1"]).kind == "ros1"
    zf, zm = locate(recordings["zstd-file"]), locate(recordings["zstd-message"])
    assert zf.compression == "file" and zf.files[0].name.endswith(".mcap.zstd")
    assert zm.compression == "message" and zf.read_by_rosbags and zm.read_by_rosbags


def _figures(obj: Any) -> Any:
    """identify.json without its wall-clock timings (``seconds``)."""
    if isinstance(obj, dict):
        return {k: _figures(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_figures(v) for v in obj]
    return obj


@pytest.mark.parametrize("kind", ["split", "db3", "ros1", "zstd-file", "zstd-message"])
def test_bag_calibrates_like_its_mcap(runs: dict[str, Path], kind: str) -> None:
    ref, got = runs["mcap"], runs[kind]
    for art in ("frames", "detections", "touchups"):
        a = read_artefact(ref / f"{art}.parquet", art)
        b = read_artefact(got / f"{art}.parquet", art)
        pd.testing.assert_frame_equal(a, b, check_exact=True)
    rec_a = json.loads((ref / "recording.json").read_text())
    rec_b = json.loads((got / "recording.json").read_text())
    assert rec_a["metadata"] == rec_b["metadata"] and rec_a["n_images"] == 75
    assert rec_a["n_joint_states"] == rec_b["n_joint_states"] > 1000
    id_a = _figures(json.loads((ref / "identify.json").read_text()))
    id_b = _figures(json.loads((got / "identify.json").read_text()))
    assert id_a == id_b and id_a["models"]["offsets"]
    # the same robot; only the provenance block differs (it names the source and its hash)
    from pipeline.export.provenance import read_provenance, strip_provenance

    a, b = ((d / "calibrated.urdf").read_text() for d in (ref, got))
    assert strip_provenance(a) == strip_provenance(b)
    assert read_provenance(a)["shipped model"] == read_provenance(b)["shipped model"]


# --------------------------------------------------------------- joint-state quirks


@pytest.fixture(scope="module")
def short_msgs() -> list[Msg]:
    """The sample's first 4 images with their joint states (ingest only)."""
    msgs, meta = sample_messages(4)
    return with_touchup_topic(msgs, meta)


def _rewrite_joints(msgs: list[Msg], fn: Any) -> list[Msg]:
    out = []
    typ = "sensor_msgs/msg/JointState"
    for topic, t, lt, data in msgs:
        if topic == "/joint_states":
            m = ROS2.deserialize_cdr(data, typ)
            names, pos = fn(list(m.name), np.asarray(m.position))
            m2 = ROS2.types[typ](
                header=m.header,
                name=names,
                position=np.asarray(pos, dtype=np.float64),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            )
            data = bytes(ROS2.serialize_cdr(m2, typ))
        out.append((topic, t, lt, data))
    return out


def _ingest(path: Path, **cfg: Any) -> tuple[pd.DataFrame, Any]:
    frames, _, info = ingest_recording(path, IngestConfig(**cfg), DetectConfig())
    return frames, info


def test_gripper_joints_shuffled_and_prefixed(short_msgs: list[Msg], tmp_path: Path) -> None:
    """Extra finger joints, a shuffled order, a name prefix: the same joint table."""
    ref = write_rosbag2(tmp_path / "ref", short_msgs, StoragePlugin.SQLITE3)
    frames_ref, info_ref = _ingest(ref)
    rng = np.random.default_rng(3)

    def gripper(names: list[str], pos: np.ndarray) -> tuple[list[str], np.ndarray]:
        n = [*names, "finger_left", "finger_right"]
        p = np.r_[pos, 0.01, 0.01]
        o = rng.permutation(len(n))  # a new order in every message
        return [n[i] for i in o], p[o]

    grip = write_ros1_bag(tmp_path / "grip.bag", _rewrite_joints(short_msgs, gripper))
    frames_g, info_g = _ingest(grip)
    pd.testing.assert_frame_equal(frames_ref, frames_g, check_exact=True)
    assert any("finger_left" in w and "ignored" in w for w in info_g.warnings)

    def prefixed(names: list[str], pos: np.ndarray) -> tuple[list[str], np.ndarray]:
        return [f"robot1/{n}" for n in names], pos

    pre = write_rosbag2(
        tmp_path / "pre", _rewrite_joints(short_msgs, prefixed), StoragePlugin.SQLITE3
    )
    with pytest.raises(BadInput) as exc:
        _ingest(pre)
    msg = str(exc.value)
    assert "\n" not in msg and "--joint-prefix" in msg and "'robot1/'" in msg and str(pre) in msg
    frames_p, info_p = _ingest(pre, joint_prefix="robot1/")
    pd.testing.assert_frame_equal(frames_ref, frames_p, check_exact=True)
    assert info_p.joint_names == info_ref.joint_names


def test_missing_chain_joint_is_one_line(short_msgs: list[Msg], tmp_path: Path) -> None:
    def drop(names: list[str], pos: np.ndarray) -> tuple[list[str], np.ndarray]:
        return names[:-1], pos[:-1]

    p = write_rosbag2(tmp_path / "drop", _rewrite_joints(short_msgs, drop), StoragePlugin.SQLITE3)
    with pytest.raises(BadInput) as exc:
        _ingest(p)
    msg = str(exc.value)
    assert "\n" not in msg and "missing" in msg and "joint_6" in msg and str(p) in msg


def test_image_topic_choice(
    short_msgs: list[Msg], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One image topic: taken whatever its name; several (no spec default among them): one
    line listing them, exit 2, and --image-topic picks; a spec default topic wins."""
    cam = "/camera/image_raw/compressed"
    left = [(("/left/image" if m[0] == cam else m[0]), *m[1:]) for m in short_msgs]
    right = [("/right/image", *m[1:]) for m in left if m[0] == "/left/image"]
    one = write_ros1_bag(tmp_path / "one.bag", left)
    _, info = _ingest(one)
    assert info.image_topic == "/left/image" and info.n_images == 4
    two = write_ros1_bag(tmp_path / "two.bag", sorted([*left, *right], key=lambda m: m[2]))
    with pytest.raises(SystemExit) as exc:
        main(["run", str(two), "--out", str(tmp_path / "out"), "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(two) in err[0] and "--image-topic" in err[0]
    assert "['/left/image', '/right/image']" in err[0]
    _, info2 = _ingest(two, image_topic="/right/image")
    assert info2.image_topic == "/right/image" and info2.n_images == 4
    with_default = sorted([*short_msgs, *right], key=lambda m: m[2])
    _, info3 = _ingest(write_rosbag2(tmp_path / "d", with_default, StoragePlugin.SQLITE3))
    assert info3.image_topic == cam


def test_not_a_bag_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exc:
        main(["run", str(tmp_path / "empty"), "--out", str(tmp_path / "out"), "-q"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metadata.yaml" in err[0] and str(tmp_path / "empty") in err[0]
    assert not (tmp_path / "out").exists()


def test_gripper_only_messages_skipped(short_msgs: list[Msg], tmp_path: Path) -> None:
    """A gripper driver's own messages on /joint_states: skipped, counted in a warning."""
    typ = "sensor_msgs/msg/JointState"
    js = [m for m in short_msgs if m[0] == "/joint_states"]
    grip = []
    for _, _, t, data in js[::10]:
        head = ROS2.deserialize_cdr(data, typ).header
        m = ROS2.types[typ](
            header=head,
            name=["finger"],
            position=np.array([0.01]),
            velocity=np.zeros(0),
            effort=np.zeros(0),
        )
        grip.append(("/joint_states", typ, t + 1, bytes(ROS2.serialize_cdr(m, typ))))
    ref = write_rosbag2(tmp_path / "ref", short_msgs, StoragePlugin.SQLITE3)
    mixed = sorted([*short_msgs, *grip], key=lambda m: m[2])
    p = write_rosbag2(tmp_path / "mixed", mixed, StoragePlugin.SQLITE3)
    frames_ref, _ = _ingest(ref)
    frames, info = _ingest(p)
    pd.testing.assert_frame_equal(frames_ref, frames, check_exact=True)
    assert any(f"{len(grip)} messages name none of the chain joints" in w for w in info.warnings)


def test_bad_bags_one_line(short_msgs: list[Msg], tmp_path: Path) -> None:
    """A metadata.yaml naming a missing file, a .bag that is not one, a touchup topic that
    is not JSON: one line naming the file, exit 2."""
    split = write_split_mcap_bag(tmp_path / "split", short_msgs, 2)
    (split / "split_1.mcap").unlink()
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\nnot really")
    bad_meta = [
        (
            TOUCHUP_TOPIC,
            STRING,
            short_msgs[0][2],
            bytes(ROS2.serialize_cdr(ROS2.types[STRING](data="polarity=dark_on_light"), STRING)),
        ),
        *short_msgs,
    ]
    notjson = write_rosbag2(tmp_path / "notjson", bad_meta, StoragePlugin.SQLITE3)
    for rec, needle in [
        (split, "lists bag file(s) ['split_1.mcap'] that are not in"),
        (junk, "not a readable ROS bag"),
        (notjson, "/touchup/metadata: not a JSON object of touchup keys"),
    ]:
        with pytest.raises(BadInput) as exc:
            _ingest(rec)
        msg = str(exc.value)
        assert "\n" not in msg and needle in msg and str(rec) in msg, msg


def test_split_bag_run_is_cached_by_content(short_msgs: list[Msg], tmp_path: Path) -> None:
    """A bag directory is hashed over its data files: same bytes -> every stage cached;
    one file changed -> a new hash (metadata.yaml itself is not hashed)."""
    from pipeline.io.fileio import file_hash
    from pipeline.io.layout import locate, recording_hash

    bag = write_split_mcap_bag(tmp_path / "split", short_msgs, 2)
    cfg = RunConfig(report=False)
    run_pipeline(bag, tmp_path / "run", cfg, until="ingest")
    again = run_pipeline(bag, tmp_path / "run", cfg, until="ingest")
    assert [r.status for r in again.stages] == ["cached"]
    h0 = recording_hash(locate(bag))
    (bag / "metadata.yaml").write_text((bag / "metadata.yaml").read_text() + "\n")
    assert recording_hash(locate(bag)) == h0
    part = bag / "split_1.mcap"
    part.write_bytes(part.read_bytes() + b"\0")
    assert recording_hash(locate(bag)) != h0
    single = tmp_path / "one.bag"
    write_ros1_bag(single, short_msgs)
    assert recording_hash(locate(single)) == file_hash(single)


@pytest.mark.parametrize("kind", ["split", "db3"])
def test_a_bag_run_shows_the_recordings_images(runs: dict[str, Path], kind: str) -> None:
    """The report reads its frames back from a bag directory as from the MCAP file
    (a rosbag2 directory was taken for a missing recording: no images)."""
    from pipeline.report.data import load_run
    from pipeline.report.images import load_images

    frames = {}
    for name in ("mcap", kind):
        data = load_run(runs[name])
        path = data.recording_path()
        assert path is not None, name
        rec = data.recording or {}
        frames[name] = load_images(path, rec.get("image_topic"), [0, 7, 74], rec.get("n_images"))
    assert sorted(frames[kind]) == sorted(frames["mcap"]) == [0, 7, 74]
    for k in frames["mcap"]:
        np.testing.assert_array_equal(frames[kind][k].gray, frames["mcap"][k].gray)
