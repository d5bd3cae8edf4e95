"""Field-recording variants (issue 34): a small simulated recording rewritten as recorders differ.

:func:`simulated` writes a small LR Mate recording with the simulator (its
truth beside it); :func:`rewrite` copies a recording message by message,
letting a function change each decoded ROS 2 message (URDF text, image
encoding, ...) and the ``touchup`` metadata, and re-encodes it with
``mcap_ros2`` as a recorder would (same chunking and compression as the
simulator). :func:`written_files_parse` checks that every URDF, JSON and
Parquet file in a run folder parses.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as RosWriter

from pipeline.io.mcap_write import msgdef as recorder_msgdef

SMALL_TOML = """
name = "field_small"
[robot]
name = "lrmate"
[camera]
width = 160
height = 128
f_px = 300.0
subsamples = 4
[targets]
count = 3
[poses]
per_target = 3
"""

#: ``edit(topic, message dict) -> message dict`` (the dict as mcap_ros2 decodes it), or
#: ``(topic, datatype, message dict)`` to write it on another topic as another type
Edit = Callable[[str, dict[str, Any]], Any]


def simulated(folder: Path, seed: int = 3, toml: str = SMALL_TOML) -> tuple[Path, dict[str, Any]]:
    """A simulated recording ``folder/sim.mcap`` and its truth (cached in the folder)."""
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import simulate

    out = folder / f"sim_{seed}.mcap"
    truth_p = folder / f"sim_{seed}.truth.json"
    if not out.exists():
        scen = folder / "field_small.toml"
        scen.write_text(toml)
        truth = simulate(load_scenario(scen), seed=seed, out=out)
        truth_p.write_text(json.dumps(truth, default=_plain))
    return out, json.loads(truth_p.read_text())


def _plain(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(type(o).__name__)


def _as_dict(msg: Any) -> Any:
    """An mcap_ros2 decoded message as plain dicts / lists / bytes."""
    if hasattr(msg, "__slots__"):
        return {k: _as_dict(getattr(msg, k)) for k in msg.__slots__}
    if isinstance(msg, list):
        return [_as_dict(x) for x in msg]
    return msg


def rewrite(
    src: Path,
    dst: Path,
    edit: Edit | None = None,
    metadata: Callable[[dict[str, str]], dict[str, str]] | None = None,
    raw: Callable[[str, dict[str, Any]], bytes | None] | None = None,
    drop_empty: bool = False,
    writer: dict[str, Any] | None = None,
) -> Path:
    """Copy a ROS 2 recording, editing messages and the ``touchup`` metadata.

    ``edit`` receives each decoded message; ``raw`` (after it) may return the
    message bytes itself, for variants the ROS 2 writer cannot produce (XCDR2).
    ``writer``: options of :class:`mcap.writer.Writer` (chunking, compression,
    indexes, summary, CRCs) instead of 64 KiB zstd chunks.
    """
    dec = DecoderFactory()
    with open(src, "rb") as f:
        r = make_reader(f)
        summ = r.get_summary()
        assert summ is not None
        msgs = []
        for sc, ch, m in r.iter_messages(log_time_order=True):
            msgs.append((sc, ch, m))
        md = {x.name: dict(x.metadata) for x in r.iter_metadata()}
    with open(dst, "wb") as f:
        if writer is None:
            w = RosWriter(f, chunk_size=65536, compression=CompressionType.ZSTD)
        else:  # the same ROS 2 encoder over an MCAP writer of these options
            import io

            from mcap.writer import Writer as McapWriter

            w = RosWriter(io.BytesIO())
            w._writer = McapWriter(f, **writer)
            w._writer.start(profile="ros2", library="vtcal-tests")
        schemas: dict[str, Any] = {}
        for sc, ch, m in msgs:
            decoder = dec.decoder_for(ch.message_encoding, sc)
            assert decoder is not None
            obj = _as_dict(decoder(m.data))
            topic, dtype = ch.topic, sc.name
            if edit is not None:
                obj = edit(ch.topic, obj)
                if isinstance(obj, tuple):
                    topic, dtype, obj = obj
            if dtype not in schemas:
                text = sc.data.decode() if dtype == sc.name else recorder_msgdef(dtype)
                schemas[dtype] = w.register_msgdef(dtype, text)
            data = raw(topic, obj) if raw is not None else None
            if data is None:
                w.write_message(
                    topic, schemas[dtype], obj, log_time=m.log_time, publish_time=m.publish_time
                )
                continue
            if topic not in w._channel_ids:
                w._channel_ids[topic] = w._writer.register_channel(
                    topic=topic, message_encoding="cdr", schema_id=schemas[dtype].id
                )
            w._writer.add_message(
                channel_id=w._channel_ids[topic],
                log_time=m.log_time,
                publish_time=m.publish_time,
                data=data,
            )
        for name, kv in md.items():
            if name == "touchup" and metadata is not None:
                kv = metadata(kv)
            if kv or not drop_empty:  # drop_empty: an emptied record is left out
                w._writer.add_metadata(name, kv)
        w.finish()
    return dst


def raw_image(msg: dict[str, Any], grey: np.ndarray, encoding: str) -> tuple[str, str, dict]:
    """A ``sensor_msgs/Image`` on ``/camera/image_raw`` of a grey image, as a camera driver
    writes it (``mono8``: uint8; ``mono16``: uint16 little-endian)."""
    px = np.ascontiguousarray(grey)
    out = {
        "header": msg["header"],
        "height": int(px.shape[0]),
        "width": int(px.shape[1]),
        "encoding": encoding,
        "is_bigendian": 0,
        "step": int(px.shape[1] * px.itemsize),
        "data": px.astype("<u2" if px.itemsize == 2 else np.uint8).tobytes(),
    }
    return "/camera/image_raw", "sensor_msgs/msg/Image", out


def png_grey(msg: dict[str, Any]) -> np.ndarray:
    """The grey pixels of a simulated ``CompressedImage`` (PNG) message."""
    import cv2

    img = cv2.imdecode(np.frombuffer(bytes(msg["data"]), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.ndim == 2
    return img


def upscaled(rec: Path, dst: Path, f: int) -> Path:
    """The same scene at ``f`` times the resolution (a driver upscaling, or an
    over-resolving lens): images resized, the pixel keys of the metadata scaled."""
    import cv2

    def up(topic: str, msg: dict) -> dict:
        if topic == "/camera/image_raw/compressed":
            g = png_grey(msg)
            big = cv2.resize(g, (g.shape[1] * f, g.shape[0] * f), interpolation=cv2.INTER_CUBIC)
            msg["data"] = cv2.imencode(".png", big)[1].tobytes()
        return msg

    def md(m: dict[str, str]) -> dict[str, str]:
        m = dict(m)
        for k in ("designated_u", "designated_v"):
            m[k] = repr((float(m[k]) + 0.5) * f - 0.5)
        for k in ("designated_size_px", "threshold_px", "threshold_size_px"):
            m[k] = repr(float(m[k]) * f)
        return m

    return rewrite(rec, dst, up, md)


def written_files_parse(folder: Path) -> list[str]:
    """Parse every URDF, JSON and Parquet file under ``folder``; return their names."""
    import xml.etree.ElementTree as ET

    import pyarrow.parquet as pq

    seen = []
    for p in sorted(folder.rglob("*")):
        if p.suffix == ".urdf":
            root = ET.fromstring(p.read_bytes())
            assert root.tag == "robot", p
        elif p.suffix == ".json":
            json.loads(p.read_text())
        elif p.suffix == ".parquet":
            pq.read_table(p)
        else:
            continue
        seen.append(p.name)
    return seen


class _Xcdr2:
    """A little-endian XCDR2 writer (8-byte values aligned to 4, as XCDR2 does)."""

    def __init__(self) -> None:
        self.b = bytearray()

    def align(self, n: int) -> None:
        self.b += b"\0" * (-len(self.b) % min(n, 4))

    def u32(self, v: int) -> None:
        self.align(4)
        self.b += struct.pack("<I", v)

    def i32(self, v: int) -> None:
        self.align(4)
        self.b += struct.pack("<i", v)

    def string(self, s: str) -> None:
        raw = s.encode() + b"\0"
        self.u32(len(raw))
        self.b += raw

    def header(self, h: dict[str, Any]) -> None:
        self.i32(h["stamp"]["sec"])
        self.u32(h["stamp"]["nanosec"])
        self.string(h["frame_id"])

    def f64s(self, xs: list[float]) -> None:
        self.u32(len(xs))
        if xs:
            self.align(8)
            self.b += struct.pack(f"<{len(xs)}d", *xs)

    def octets(self, data: bytes) -> None:
        self.u32(len(data))
        self.b += bytes(data)


def xcdr2(topic: str, msg: dict[str, Any], delimited: bool = False) -> bytes:
    """A ROS 2 message (String, JointState, Image, CompressedImage) in XCDR2, little-endian.

    ``delimited``: the ``D_CDR2_LE`` encapsulation of an appendable type (a
    DHEADER, the body's length, before the body); else ``CDR2_LE`` (final types).
    """
    w = _Xcdr2()
    if "data" in msg and isinstance(msg["data"], str):
        w.string(msg["data"])
    elif "position" in msg:
        w.header(msg["header"])
        w.u32(len(msg["name"]))
        for n in msg["name"]:
            w.string(n)
        for k in ("position", "velocity", "effort"):
            w.f64s([float(x) for x in msg[k]])
    elif "format" in msg:
        w.header(msg["header"])
        w.string(msg["format"])
        w.octets(msg["data"])
    else:
        w.header(msg["header"])
        w.u32(msg["height"])
        w.u32(msg["width"])
        w.string(msg["encoding"])
        w.b += bytes([msg["is_bigendian"]])
        w.u32(msg["step"])
        w.octets(msg["data"])
    body = bytes(w.b)
    if delimited:
        return b"\x00\x09\x00\x00" + struct.pack("<I", len(body)) + body
    return b"\x00\x07\x00\x00" + body
