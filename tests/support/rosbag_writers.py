"""Bags written by ``rosbags``' own writers (independent of vtcal's MCAP writer and
readers), from the shipped sample's messages: a split-MCAP rosbag2 directory, a
sqlite3 (``.db3``) bag, a ROS 1 ``.bag``. Used by tests/test_ros_bags.py and
benchmarks/bench_ros_bags.py.

The ROS 1 messages are built field by field from the ROS 2 ones (``Header.seq`` = 0).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from pipeline.io.recording import TOUCHUP_TOPIC

REPO = Path(__file__).resolve().parents[2]
SAMPLE = REPO / "datasets" / "samples" / "sample_lrmate.mcap"
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)
STRING = "std_msgs/msg/String"

Msg = tuple[str, str, int, bytes]  # topic, type, log time (ns), ROS 2 CDR


def sample_messages(n_images: int | None = None) -> tuple[list[Msg], dict[str, str]]:
    """The sample's messages (all, or up to 0.3 s after its ``n_images``-th image) and its
    ``touchup`` metadata; every message byte for byte, in log-time order."""
    out: list[Msg] = []
    with SAMPLE.open("rb") as f:
        r = make_reader(f)
        meta = next(dict(m.metadata) for m in r.iter_metadata() if m.name == "touchup")
        seen, stop = 0, None
        for sc, ch, m in r.iter_messages(log_time_order=True):
            if stop is not None and m.log_time > stop:
                break
            out.append((ch.topic, sc.name if sc else "", m.log_time, bytes(m.data)))
            if "Image" in (sc.name if sc else ""):
                seen += 1
                if seen == n_images:
                    stop = m.log_time + 300_000_000
    return out, meta


def with_touchup_topic(msgs: list[Msg], meta: dict[str, str]) -> list[Msg]:
    """The touch-up metadata as the first message of :data:`TOUCHUP_TOPIC` (a JSON object)."""
    data = ROS2.serialize_cdr(ROS2.types[STRING](data=json.dumps(meta)), STRING)
    return [(TOUCHUP_TOPIC, STRING, msgs[0][2], bytes(data)), *msgs]


def write_rosbag2(
    path: Path, msgs: list[Msg], storage: StoragePlugin, compression: str = ""
) -> Path:
    """A rosbag2 bag directory; ``compression`` ``file`` or ``message`` compresses it with
    zstd as ``ros2 bag record --compression-mode ... --compression-format zstd`` does."""
    w = Writer2(path, version=9, storage_plugin=storage)
    if compression:
        w.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    with w:
        conns: dict[str, Any] = {}
        for topic, typ, t, data in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ROS2)
            w.write(conns[topic], t, data)
    return path


def write_split_mcap_bag(path: Path, msgs: list[Msg], parts: int) -> Path:
    """One bag directory of ``parts`` split .mcap files (as ``ros2 bag record --max-bag-size``).

    Each part is written by rosbags' MCAP writer; the directory's metadata.yaml is
    the first part's with every file listed and the message counts summed.
    """
    tmp = path.parent / f"{path.name}.parts"
    cut = np.linspace(0, len(msgs), parts + 1).astype(int)
    # the URDF (latched in a real recorder) goes into every part, like a transient-local topic
    latched = [m for m in msgs if m[0] == "/robot_description"]
    dirs = []
    for i in range(parts):
        part = msgs[cut[i] : cut[i + 1]]
        if i > 0:
            part = latched + part
        dirs.append(write_rosbag2(tmp / f"part{i}", part, StoragePlugin.MCAP))
    path.mkdir()
    yaml = YAML(typ="safe")
    metas = [yaml.load((d / "metadata.yaml").read_text()) for d in dirs]
    info = metas[0]["rosbag2_bagfile_information"]
    names = []
    for i, d in enumerate(dirs):
        (f,) = d.glob("*.mcap")
        name = f"{path.name}_{i}.mcap"
        shutil.move(str(f), path / name)
        names.append(name)
    counts: dict[str, int] = {}
    for m in metas:
        for t in m["rosbag2_bagfile_information"]["topics_with_message_count"]:
            counts[t["topic_metadata"]["name"]] = (
                counts.get(t["topic_metadata"]["name"], 0) + t["message_count"]
            )
    for t in info["topics_with_message_count"]:
        t["message_count"] = counts[t["topic_metadata"]["name"]]
    info["relative_file_paths"] = names
    info["message_count"] = sum(counts.values())
    info.pop("files", None)
    with (path / "metadata.yaml").open("w") as fh:
        yaml.dump(metas[0], fh)
    shutil.rmtree(tmp)
    return path


def to_ros1(msg: Any) -> Any:
    """A ROS 2 message as the ROS 1 (Noetic) type: same fields, ``Header.seq`` = 0."""
    cls = ROS1.types[msg.__msgtype__]
    kw = {}
    for f in dataclasses.fields(cls):
        if f.name.startswith("__"):
            continue
        if f.name == "seq":
            kw["seq"] = 0
            continue
        v = getattr(msg, f.name)
        kw[f.name] = to_ros1(v) if hasattr(v, "__msgtype__") else v
    return cls(**kw)


def write_ros1_bag(path: Path, msgs: list[Msg]) -> Path:
    with Writer1(path) as w:
        conns: dict[str, Any] = {}
        for topic, typ, t, data in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ROS1)
            m1 = to_ros1(ROS2.deserialize_cdr(data, typ))
            w.write(conns[topic], t, bytes(ROS1.serialize_ros1(m1, typ)))
    return path
