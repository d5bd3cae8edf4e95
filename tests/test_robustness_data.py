"""Bad-input builders shared by the robustness, fuzz and kill tests (no tests here).

A tiny valid recording (a two-joint arm, a handful of 64x48 images) that the
bad-input variants start from, MCAP surgery (record walking, chunk spans,
re-logging messages with other log times), a raw-image writer that can lie
about ``step``/``height``, a valid synthetic touch-up table, and an in-process
CLI driver that returns the exit code and the stderr lines.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as RosWriter
from support.mcap_write import msgdef, write_recording

URDF = """<?xml version="1.0"?>
<robot name="two">
  <link name="base_link"/><link name="l1"/><link name="flange"/>
  <joint name="j1" type="revolute"><parent link="base_link"/><child link="l1"/>
    <origin xyz="0 0 0.3" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="flange"/>
    <origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
</robot>
"""
NAMES = ["j1", "j2"]
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
W, H = 64, 48


def disc(u: float, v: float, r: float = 8.0) -> np.ndarray:
    """A dark disc on a light plate, (H, W) uint8 (hard edge: fast, good enough here)."""
    vv, uu = np.mgrid[0:H, 0:W]
    return np.where(np.hypot(uu - u, vv - v) <= r, 40, 200).astype(np.uint8)


def q_of_t(t_ns: int) -> np.ndarray:
    s = (t_ns - T0) / 1e9
    x = np.clip(s - 0.5, 0.0, 0.5)
    return np.array([0.1 + 0.2 * x, -0.3 + 0.1 * x])


def tiny_recording(path: Path, n_img: int = 4, n_js: int = 120, **kw: Any) -> Path:
    """A valid recording: URDF, ``n_js`` joint states at 100 Hz, ``n_img`` images, metadata."""
    joints = kw.pop("joints", [(T0 + k * 10 * MS, q_of_t(T0 + k * 10 * MS)) for k in range(n_js)])
    stamps = [T0 + int((0.1 + 0.25 * i) * 1e9) for i in range(n_img)]
    images = kw.pop("images", [(t, disc(30.3 + i, 22.7)) for i, t in enumerate(stamps)])
    write_recording(
        path,
        urdf=kw.pop("urdf", URDF),
        joint_names=kw.pop("joint_names", NAMES),
        joints=joints,
        images=images,
        metadata=kw.pop("metadata", {"polarity": "dark_on_light", "designated_size_px": "16"}),
        **kw,
    )
    return path


# ------------------------------------------------------------------ MCAP surgery


def records(data: bytes) -> list[tuple[int, int, int]]:
    """``(opcode, start, end)`` of every top-level record after the magic, in file order.

    Stops at the first record that runs past the end of the data.
    """
    out = []
    pos = 8
    while pos + 9 <= len(data):
        op = data[pos]
        (n,) = struct.unpack_from("<Q", data, pos + 1)
        end = pos + 9 + n
        if end > len(data):
            break
        out.append((op, pos, end))
        pos = end
        if op == 0x02:  # footer
            break
    return out


CHUNK = 0x06


def chunk_spans(data: bytes) -> list[tuple[int, int]]:
    """``(start, end)`` byte spans of the Chunk records."""
    return [(a, b) for op, a, b in records(data) if op == CHUNK]


def relog(src: Path, dst: Path, new_log_time: Callable[[str, int, int], int]) -> None:
    """Copy a recording, giving message ``k`` of ``topic`` the log time ``f(topic, k, t)``.

    Header stamps are unchanged, so moving a message in log time makes its
    stamp go backwards (or repeat) in log-time order.
    """
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        msgs = []
        counts: dict[str, int] = {}
        for _sc, ch, m in reader.iter_messages(log_time_order=False):
            k = counts.get(ch.topic, 0)
            counts[ch.topic] = k + 1
            msgs.append((new_log_time(ch.topic, k, m.log_time), ch.id, m))
        metadata = [(md.name, dict(md.metadata)) for md in reader.iter_metadata()]
    msgs.sort(key=lambda e: e[0])
    with open(dst, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE)
        w.start(profile="ros2")
        sid = {}
        for s in summary.schemas.values():
            sid[s.id] = w.register_schema(s.name, s.encoding, s.data)
        cid = {}
        for c in summary.channels.values():
            cid[c.id] = w.register_channel(c.topic, c.message_encoding, sid[c.schema_id])
        for t, ch_id, m in msgs:
            w.add_message(cid[ch_id], log_time=t, data=m.data, publish_time=t, sequence=m.sequence)
        for name, md in metadata:
            w.add_metadata(name, md)
        w.finish()


def raw_image_recording(path: Path, images: list[dict[str, Any]]) -> Path:
    """A recording whose ``sensor_msgs/Image`` fields are written as given (may be inconsistent).

    Each item: ``height, width, step, encoding, data`` (bytes) and optional ``stamp_ns``.
    """
    with open(path, "wb") as f:
        w = RosWriter(f, compression=CompressionType.NONE)
        s_str = w.register_msgdef("std_msgs/msg/String", msgdef("std_msgs/msg/String", False))
        s_js = w.register_msgdef(
            "sensor_msgs/msg/JointState", msgdef("sensor_msgs/msg/JointState", False)
        )
        s_img = w.register_msgdef("sensor_msgs/msg/Image", msgdef("sensor_msgs/msg/Image", False))
        w.write_message("/robot_description", s_str, {"data": URDF}, log_time=T0 - MS)
        for k in range(120):
            t = T0 + k * 10 * MS
            w.write_message(
                "/joint_states",
                s_js,
                {
                    "header": {"stamp": _stamp(t), "frame_id": ""},
                    "name": NAMES,
                    "position": [float(x) for x in q_of_t(t)],
                    "velocity": [],
                    "effort": [],
                },
                log_time=t,
            )
        for i, im in enumerate(images):
            t = im.get("stamp_ns", T0 + (100 + 250 * i) * MS)
            msg = {
                "header": {"stamp": _stamp(t), "frame_id": "camera"},
                "height": im["height"],
                "width": im["width"],
                "encoding": im.get("encoding", "mono8"),
                "is_bigendian": 0,
                "step": im["step"],
                "data": bytes(im["data"]),
            }
            w.write_message("/camera/image_raw", s_img, msg, log_time=t + 30 * MS)
        w.finish()
    return path


def compressed_recording(path: Path, fmt: str, payloads: list[bytes]) -> Path:
    """A recording of ``sensor_msgs/CompressedImage`` messages with this ``format`` and data."""
    with open(path, "wb") as f:
        w = RosWriter(f, compression=CompressionType.NONE)
        s_str = w.register_msgdef("std_msgs/msg/String", msgdef("std_msgs/msg/String", False))
        s_js = w.register_msgdef(
            "sensor_msgs/msg/JointState", msgdef("sensor_msgs/msg/JointState", False)
        )
        s_img = w.register_msgdef(
            "sensor_msgs/msg/CompressedImage", msgdef("sensor_msgs/msg/CompressedImage", False)
        )
        w.write_message("/robot_description", s_str, {"data": URDF}, log_time=T0 - MS)
        for k in range(60):
            t = T0 + k * 10 * MS
            js = {
                "header": {"stamp": _stamp(t), "frame_id": ""},
                "name": NAMES,
                "position": [float(x) for x in q_of_t(t)],
                "velocity": [],
                "effort": [],
            }
            w.write_message("/joint_states", s_js, js, log_time=t)
        for i, data in enumerate(payloads):
            t = T0 + (100 + 100 * i) * MS
            msg = {
                "header": {"stamp": _stamp(t), "frame_id": "camera"},
                "format": fmt,
                "data": data,
            }
            w.write_message("/camera/image_raw/compressed", s_img, msg, log_time=t + 30 * MS)
        w.finish()
    return path


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


# ------------------------------------------------------------------ touch-up tables

PIN = np.array([0.0167, -0.0101, 0.2524])
LRMATE_CENTRE = np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32])


def touchup_table(
    seed: int = 0, per_target: int = 8, n_targets: int = 3
) -> tuple[pd.DataFrame, str]:
    """A valid touch-up table of the built-in LR Mate (nominal = true) and its URDF."""
    from pipeline.accuracy.evaluate import synthetic_touchups
    from pipeline.kinematics import load_chain
    from pipeline.robots import builtin_urdf

    urdf = builtin_urdf("lrmate")
    chain = load_chain(urdf, "base_link", "flange")
    table, _ = synthetic_touchups(
        chain,
        PIN,
        n_targets,
        per_target,
        np.random.default_rng(seed),
        noise_pin_m=2e-5,
        q_centre=LRMATE_CENTRE,
    )
    return table, urdf


# ------------------------------------------------------------------ the CLI in-process


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """Run ``vtcal ARGS`` in-process; return ``(exit code, non-empty stderr lines)``."""
    from pipeline.cli import main

    capsys.readouterr()
    code = 0
    try:
        main(args)
    except SystemExit as exc:
        code = int(exc.code or 0)
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    return code, err
