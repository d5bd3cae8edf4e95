"""Streaming MCAP access for recordings (spec/recording.md).

One linear pass over the file (:func:`pipeline.io.mcap_records.file_records`;
chunks are decompressed one at a time, so memory is bounded by one chunk, and
read by :func:`pipeline.io.mcap_records.chunk_records`),
and small hand-written decoders for the few message types a recording holds:

- ROS 2 CDR (``ros2msg`` schemas): ``std_msgs/String``, ``sensor_msgs/JointState``,
  ``sensor_msgs/Image``, ``sensor_msgs/CompressedImage``. The CDR layout of these
  types is fixed, so the decoders read it directly (``numpy.frombuffer`` for the
  arrays) and never parse the schema text: ``MSG: pkg/Type`` and
  ``MSG: pkg/msg/Type`` lines, comments and constants are all equally fine.
- Foxglove ``foxglove.RawImage`` / ``foxglove.CompressedImage`` in JSON, and in
  protobuf when ``foxglove-schemas-protobuf`` is installed (the ``foxglove`` extra).

A truncated file (recorder killed) ends the stream early; :class:`StreamState`
records that and how many bytes were read.
"""

from __future__ import annotations

import base64
import json
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from mcap.records import Channel, Chunk, Message, Metadata, Schema

from pipeline.errors import BadInput
from pipeline.io.mcap_records import chunk_records, file_records

# an image that does not decode is reported by vtcal (frame flagged, one warning line):
# OpenCV's own warnings on stderr would only repeat it
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)

IMAGE_TYPES = {
    "sensor_msgs/Image": "ros_image",
    "sensor_msgs/msg/Image": "ros_image",
    "sensor_msgs/CompressedImage": "ros_compressed",
    "sensor_msgs/msg/CompressedImage": "ros_compressed",
    "foxglove.RawImage": "fox_raw",
    "foxglove.CompressedImage": "fox_compressed",
    "foxglove_msgs/RawImage": "fox_raw",
    "foxglove_msgs/msg/RawImage": "fox_raw",
    "foxglove_msgs/CompressedImage": "fox_compressed",
    "foxglove_msgs/msg/CompressedImage": "fox_compressed",
}
JOINT_TYPES = {"sensor_msgs/JointState", "sensor_msgs/msg/JointState"}
STRING_TYPES = {"std_msgs/String", "std_msgs/msg/String"}
DEFAULT_IMAGE_TOPICS = ("/camera/image_raw", "/camera/image_raw/compressed")


@dataclass
class StreamState:
    """What one pass over a file saw (filled in while streaming)."""

    path: str
    file_size: int = 0
    bytes_read: int = 0
    truncated: bool = False
    error: str = ""
    #: one line per chunk skipped because its CRC failed or it did not decompress/parse
    bad_chunks: list[str] = field(default_factory=list)
    #: messages skipped because no Channel record for them was seen (lost with a damaged chunk)
    orphan_messages: int = 0
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    def topic_type(self, channel_id: int) -> tuple[str, str, str]:
        """``(topic, schema name, message encoding)`` of a channel."""
        ch = self.channels[channel_id]
        sc = self.schemas.get(ch.schema_id)
        return ch.topic, (sc.name if sc is not None else ""), ch.message_encoding


class _CountingFile:
    """A read-only binary file wrapper counting the bytes handed out."""

    def __init__(self, f: Any) -> None:
        self._f = f
        self.count = 0

    def read(self, n: int = -1) -> bytes:
        b: bytes = self._f.read(n)
        self.count += len(b)
        return b

    def read1(self, n: int = -1) -> bytes:  # pragma: no cover - not used by mcap
        return self.read(n)


def iter_messages(path: str | os.PathLike[str], state: StreamState) -> Iterator[Message]:
    """Yield every Message record of ``path`` in file order, filling ``state``.

    Schemas, channels and metadata records are collected into ``state`` as
    they pass (they precede the messages that use them). A file that ends early
    or breaks mid-record stops the iteration with ``state.truncated`` set.

    Raises
    ------
    BadInput
        If the file is missing or not an MCAP file at all.
    """
    path = os.fspath(path)
    try:
        state.file_size = os.path.getsize(path)
        fh = open(path, "rb", buffering=1 << 20)  # noqa: SIM115 - closed below
    except OSError as exc:
        raise BadInput(f"{path}: cannot open: {exc.strerror}") from exc
    with fh:
        head = fh.read(8)
        if not head.startswith(b"\x89MCAP"):
            raise BadInput(f"{path}: not an MCAP file (bad magic {head[:5]!r})")
        fh.seek(0)
        cf = _CountingFile(fh)
        # chunks are opened here, one at a time, so that one whose CRC fails (or that does
        # not decompress) is skipped and reported instead of ending the stream
        seen_footer = False
        try:
            for outer in file_records(cf):  # type: ignore[arg-type]
                if outer is None:  # an index or other record the pass does not need
                    state.bytes_read = cf.count
                    continue
                if isinstance(outer, Chunk):
                    try:
                        inner = chunk_records(outer)
                    except Exception as exc:  # noqa: BLE001 - CRC, zstd/lz4, record parse
                        state.bad_chunks.append(
                            f"chunk ending at byte {cf.count} (log time {outer.message_start_time}"
                            f"..{outer.message_end_time} ns, {len(outer.data)} bytes): "
                            f"{type(exc).__name__}: {exc}"[:240]
                        )
                        continue
                else:
                    inner = [outer]
                for rec in inner:
                    if isinstance(rec, Message):
                        if rec.channel_id in state.channels:
                            yield rec
                        else:
                            state.orphan_messages += 1
                    elif isinstance(rec, Schema):
                        state.schemas[rec.id] = rec
                    elif isinstance(rec, Channel):
                        state.channels[rec.id] = rec
                    elif isinstance(rec, Metadata):
                        state.metadata[rec.name] = dict(rec.metadata)
                    elif type(rec).__name__ == "Footer":
                        seen_footer = True
                state.bytes_read = cf.count  # end of the last complete record
        except Exception as exc:  # noqa: BLE001 - any break in the stream is truncation
            state.truncated = True
            state.error = (f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)[:200]
        if not state.truncated:
            state.bytes_read = cf.count
        if not seen_footer and not state.truncated:
            state.truncated = True
            state.error = "no footer"


# --------------------------------------------------------------------------- CDR


#: CDR encapsulation identifiers (first two bytes, big-endian) -> name; the plain ones
#: vtcal reads: classic CDR and XCDR2 of final types (PLAIN_CDR2), either byte order
ENCAPSULATIONS = {
    0x0000: "CDR_BE",
    0x0001: "CDR_LE",
    0x0002: "PL_CDR_BE",
    0x0003: "PL_CDR_LE",
    0x0006: "CDR2_BE",
    0x0007: "CDR2_LE",
    0x0008: "D_CDR2_BE",
    0x0009: "D_CDR2_LE",
    0x000A: "PL_CDR2_BE",
    0x000B: "PL_CDR2_LE",
}
_PLAIN = {0x0000: 8, 0x0001: 8, 0x0006: 4, 0x0007: 4}  # id -> largest alignment


class _Cdr:
    """Minimal little/big-endian CDR cursor over one message (offsets after the 4-byte header).

    Reads classic CDR (XCDR1: 8-byte values aligned to 8) and plain XCDR2
    (``CDR2_LE/BE``, what a DDS writing XCDR2 sends for ROS 2's final types:
    8-byte values aligned to 4). Delimited and parameter-list encapsulations
    (appendable/mutable types) raise ``ValueError`` naming the encapsulation.
    """

    __slots__ = ("buf", "pos", "e", "max_align")

    def __init__(self, buf: bytes) -> None:
        if len(buf) < 4:
            raise ValueError("message shorter than the CDR header")
        self.buf = buf
        self.pos = 4
        rep = (buf[0] << 8) | buf[1]
        if rep not in _PLAIN:
            name = ENCAPSULATIONS.get(rep, "unknown")
            raise ValueError(
                f"CDR encapsulation {name} (0x{rep:04x}) is not read: vtcal reads CDR_LE/BE "
                "and XCDR2 CDR2_LE/BE (ROS 2 messages of final types)"
            )
        self.e = "<" if buf[1] & 1 else ">"
        self.max_align = _PLAIN[rep]

    def align(self, n: int) -> None:
        r = (self.pos - 4) % n
        if r:
            self.pos += n - r

    def u8(self) -> int:
        v = self.buf[self.pos]
        self.pos += 1
        return v

    def u32(self) -> int:
        self.align(4)
        (v,) = struct.unpack_from(self.e + "I", self.buf, self.pos)
        self.pos += 4
        return int(v)

    def i32(self) -> int:
        self.align(4)
        (v,) = struct.unpack_from(self.e + "i", self.buf, self.pos)
        self.pos += 4
        return int(v)

    def string(self) -> str:
        n = self.u32()
        s = self.buf[self.pos : self.pos + max(n - 1, 0)]
        self.pos += n
        return s.decode("utf-8", errors="replace")

    def strings(self) -> list[str]:
        return [self.string() for _ in range(self.u32())]

    def f64s(self) -> np.ndarray:
        n = self.u32()
        if n:
            self.align(min(8, self.max_align))
        a = np.frombuffer(self.buf, dtype=self.e + "f8", count=n, offset=self.pos)
        self.pos += 8 * n
        return a.astype(np.float64)

    def bytes_(self) -> memoryview:
        n = self.u32()
        if self.pos + n > len(self.buf):
            raise ValueError("byte array runs past the message end")
        v = memoryview(self.buf)[self.pos : self.pos + n]
        self.pos += n
        return v

    def stamp_ns(self) -> tuple[int, str]:
        sec = self.i32()
        nsec = self.u32()
        frame = self.string()
        return sec * 1_000_000_000 + nsec, frame


def decode_string(data: bytes) -> str:
    """``std_msgs/String`` CDR -> its text."""
    return _Cdr(data).string()


#: the last joint-state layout read by :func:`decode_joint_state`: ``(header, bytes 12..k,
#: names, k, byte order, 8-byte alignment)``, ``k`` the offset after the name list
_JOINT_LAYOUT: list[tuple[bytes, bytes, list[str], int, str, int] | None] = [None]


def decode_joint_state(data: bytes) -> tuple[int, list[str], np.ndarray]:
    """``sensor_msgs/JointState`` CDR -> ``(stamp_ns, names, positions (n,))``.

    A recording's joint states share one layout: the same encapsulation, frame id
    and names, only the stamp (bytes 4-12) and the values change. When a message's
    bytes ``0..4`` and ``12..k`` (frame id and names) equal the last message's, its
    names and the offset of its positions are the last message's, and only the stamp
    and the positions are read (a few microseconds instead of ~40 of parsing; the
    same values, ``tests/test_io_mcap_joints.py``).
    """
    lay = _JOINT_LAYOUT[0]
    if lay is not None:
        head, mid, names, k, e, a8 = lay
        if data[:4] == head and data[12:k] == mid and len(data) >= k + 4:
            sec, nsec = struct.unpack_from(e + "iI", data, 4)
            p = k + (-(k - 4) % 4)
            (n,) = struct.unpack_from(e + "I", data, p)
            p += 4
            if n:
                p += -(p - 4) % a8
            if p + 8 * n <= len(data):
                pos = np.frombuffer(data, dtype=e + "f8", count=n, offset=p)
                return sec * 1_000_000_000 + nsec, list(names), pos.astype(np.float64)
    c = _Cdr(data)
    stamp, _ = c.stamp_ns()
    names = c.strings()
    k = c.pos
    pos = c.f64s()
    _JOINT_LAYOUT[0] = (
        bytes(data[:4]),
        bytes(data[12:k]),
        list(names),
        k,
        c.e,
        min(8, c.max_align),
    )
    return stamp, names, pos


@dataclass
class EncodedImage:
    """An image message before pixel decoding."""

    stamp_ns: int
    kind: str  # "raw" or "compressed"
    encoding: str  # raw: mono8, rgb8, ...; compressed: png, jpeg, ...
    height: int = 0
    width: int = 0
    step: int = 0
    bigendian: bool = False
    data: bytes | memoryview = b""


def decode_image_message(schema_name: str, msg_encoding: str, data: bytes) -> EncodedImage:
    """Any supported image message -> :class:`EncodedImage` (pixels not yet decoded)."""
    kind = IMAGE_TYPES[schema_name]
    if kind == "ros_image":
        c = _Cdr(data)
        stamp, _ = c.stamp_ns()
        h = c.u32()
        w = c.u32()
        enc = c.string()
        big = bool(c.u8())
        step = c.u32()
        return EncodedImage(stamp, "raw", enc, h, w, step, big, c.bytes_())
    if kind == "ros_compressed":
        c = _Cdr(data)
        stamp, _ = c.stamp_ns()
        fmt = c.string()
        return EncodedImage(stamp, "compressed", fmt, data=c.bytes_())
    obj = _foxglove_object(schema_name, msg_encoding, data)
    ts = obj.get("timestamp") or {}
    if isinstance(ts, dict):
        stamp = int(ts.get("sec", 0)) * 1_000_000_000 + int(ts.get("nsec", 0))
    else:
        stamp = int(ts)
    payload = obj.get("data", b"")
    if isinstance(payload, str):
        payload = base64.b64decode(payload)
    if kind == "fox_raw":
        return EncodedImage(
            stamp,
            "raw",
            str(obj.get("encoding", "")),
            int(obj.get("height", 0)),
            int(obj.get("width", 0)),
            int(obj.get("step", 0)),
            False,
            payload,
        )
    return EncodedImage(stamp, "compressed", str(obj.get("format", "")), data=payload)


def _foxglove_object(schema_name: str, msg_encoding: str, data: bytes) -> dict[str, Any]:
    if msg_encoding == "json":
        out: dict[str, Any] = json.loads(bytes(data))
        return out
    if msg_encoding == "protobuf":
        import importlib

        name = "RawImage" if schema_name.endswith("RawImage") else "CompressedImage"
        try:
            mod = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
        except ImportError as exc:
            raise ValueError(
                "Foxglove protobuf images need the foxglove extra: pip install 'vtcal[foxglove]'"
            ) from exc
        m: Any = getattr(mod, name)()
        m.ParseFromString(bytes(data))
        res: dict[str, Any] = {
            "timestamp": {"sec": m.timestamp.seconds, "nsec": m.timestamp.nanos},
            "data": bytes(m.data),
        }
        for k in ("encoding", "format", "height", "width", "step"):
            if hasattr(m, k):
                res[k] = getattr(m, k)
        return res
    raise ValueError(f"unsupported message encoding {msg_encoding!r}")


RAW_ENCODINGS = {
    "mono8",
    "8uc1",
    "rgb8",
    "bgr8",
    "rgba8",
    "bgra8",
    "mono16",
    "16uc1",
}


def image_to_gray(img: EncodedImage) -> np.ndarray:
    """Decode pixels to a 2-D grey image (uint8 or uint16, a view where possible).

    Colour images are reduced to grey by :func:`colour_to_grey` (the mean of the
    colour channels). Raises ``ValueError`` naming the encoding when it is not
    supported.
    """
    if img.kind == "raw":
        enc = img.encoding.lower()
        h, w, step = img.height, img.width, img.step
        if enc not in RAW_ENCODINGS:
            raise ValueError(f"unknown image encoding {img.encoding!r}")
        buf = np.frombuffer(img.data, dtype=np.uint8)
        if step == 0:
            step = w * {"mono16": 2, "16uc1": 2, "rgb8": 3, "bgr8": 3}.get(
                enc, 4 if "a8" in enc else 1
            )
        if h <= 0 or w <= 0 or buf.size != h * step:
            raise ValueError(
                f"image {w}x{h} step {step}: {buf.size} bytes of data, step*height = {h * step}"
            )
        bpp = {"mono16": 2, "16uc1": 2, "rgb8": 3, "bgr8": 3}.get(enc, 4 if "a8" in enc else 1)
        if step < w * bpp:
            raise ValueError(f"image {w}x{h} {img.encoding}: step {step} < width*{bpp}")
        rows = buf[: h * step].reshape(h, step)
        if enc in ("mono8", "8uc1"):
            return rows[:, :w]
        if enc in ("mono16", "16uc1"):
            dt = ">u2" if img.bigendian else "<u2"
            return rows[:, : 2 * w].copy().view(dt).reshape(h, w).astype(np.uint16)
        nch = 3 if enc in ("rgb8", "bgr8") else 4
        px = np.ascontiguousarray(rows[:, : nch * w]).reshape(h, w, nch)
        return colour_to_grey(px)
    fmt = img.encoding.lower()
    if not any(k in fmt for k in ("png", "jpeg", "jpg", "tiff", "bmp", "webp")):
        raise ValueError(f"unknown compressed image format {img.encoding!r}")
    arr = np.frombuffer(img.data, dtype=np.uint8)
    out = cv2.imdecode(arr, cv2.IMREAD_UNCHANGED)
    if out is None:
        raise ValueError(f"compressed image ({img.encoding!r}) does not decode")
    if out.ndim == 3:
        out = colour_to_grey(out)
    return out


#: the sample depths a 16-bit image may carry (a 12-bit sensor's data in ``mono16``)
SENSOR_BITS = (10, 12, 14, 16)


def significant_bits(grey: np.ndarray) -> int:
    """Bits a ``uint16`` image uses: the smallest of :data:`SENSOR_BITS` that holds its maximum.

    A camera driver publishes a 10-, 12- or 14-bit sensor's samples in
    ``mono16`` unscaled, so the data stop at ``2^b - 1``; the depth is read
    from the data, since the message does not say it.
    """
    top = int(grey.max()) if grey.size else 0
    return next(b for b in SENSOR_BITS if top < (1 << b))


def to_full_range(grey: np.ndarray, bits: int) -> np.ndarray:
    """``bits``-deep samples in a ``uint16`` image stretched to the full 16-bit range.

    ``I' = round(I (2^16 - 1) / (2^b - 1))`` (clipped at ``2^16 - 1``), so the
    top code of the sensor becomes the top code of the type: the response
    curve (``g^-1(I / 65535)``) and the clip level then mean what they mean
    for a 16-bit sensor. ``bits`` 16 returns the image as it is.
    """
    if bits >= 16:
        return grey
    top = (1 << bits) - 1
    wide = (grey.astype(np.uint32) * 65535 + top // 2) // top
    return np.minimum(wide, 65535).astype(np.uint16)


def colour_to_grey(px: np.ndarray) -> np.ndarray:
    """Grey of a colour image: the mean of its three colour channels, rounded (uint8).

    ``I = rint((c_0 + c_1 + c_2) / 3)``, alpha (a fourth channel) ignored; the
    channel order does not matter. Equal weights, not luma weights (ITU-R BT.601
    ``0.299 R + 0.587 G + 0.114 B``): behind a Bayer mosaic each channel is
    interpolated from other photosites, and on a neutral target their
    interpolation errors at an edge differ by channel and cancel in the plain
    mean far better than in the luma sum. Measured on rendered 54 px discs
    behind an RGGB mosaic, shot noise and 2 grey levels of noise, 60 images
    (``docs/detection.md``): centre RMS 0.0040 px and long-axis scatter 0.0078 px
    with the mean, 0.0061 / 0.0109 px with luma weights, 0.0041 / 0.0075 px
    for the same sensor without the mosaic (bilinear demosaicing; OpenCV's
    edge-aware one likewise, its VNG about equal either way).

    Parameters
    ----------
    px : (H, W, 3 or 4) uint8 or uint16

    Returns
    -------
    (H, W) of the same dtype
    """
    c = px[:, :, :3]
    total = c[:, :, 0].astype(np.uint32) + c[:, :, 1] + c[:, :, 2]
    return ((total + 1) // 3).astype(px.dtype)
