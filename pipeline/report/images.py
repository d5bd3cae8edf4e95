"""Camera images for the report and the Rerun recording, fetched again from the recording.

Images are not artefacts (a run folder stays small); when the recording named
in ``recording.json`` is still reachable, the few images the report shows are
read back from it by frame index (the 0-based index of the image message on
the image topic in log-time order, ties in file order, as ingest numbers
them): through the MCAP index when the file has one that agrees with ingest's
count, else in a streaming pass. When it is not reachable, the outputs simply
go without images.
"""

from __future__ import annotations

import base64
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from pipeline.io.layout import locate
from pipeline.io.mcap import (
    DEFAULT_IMAGE_TOPICS,
    IMAGE_TYPES,
    EncodedImage,
    StreamState,
    decode_image_message,
    image_to_gray,
)
from pipeline.io.mcap_index import topic_messages
from pipeline.io.recording import iter_recording

if TYPE_CHECKING:
    from pipeline.report.data import RunData


@dataclass
class Frame:
    """One image read back from a recording.

    Attributes
    ----------
    gray : (H, W) uint8, decoded on first use (the Rerun recording passes a
        PNG/JPEG's own bytes on and never needs the pixels)
    encoded : bytes or None
        The message's own PNG/JPEG bytes for a compressed image (re-used as
        they are by the Rerun recording), None for a raw image.
    media_type : str
        ``image/png`` or ``image/jpeg`` when ``encoded`` is set.
    """

    message: EncodedImage = field(repr=False)
    encoded: bytes | None = None
    media_type: str = ""

    @cached_property
    def gray(self) -> np.ndarray:
        """The grey image, (H, W) uint8."""
        return _to_u8(image_to_gray(self.message))

    @cached_property
    def rrd_blob(self) -> tuple[bytes, str]:
        """``(bytes, media type)`` run.rrd logs: the message's own PNG/JPEG bytes, else
        the grey image as PNG (:func:`png_bytes`)."""
        if self.encoded is not None:
            return self.encoded, self.media_type
        return png_bytes(self.gray), "image/png"


def load_images(
    path: Path,
    image_topic: str | None,
    indices: Iterable[int],
    n_images: int | None = None,
) -> dict[int, Frame]:
    """The wanted frames ``{frame index: Frame}`` of a recording.

    Parameters
    ----------
    path : the recording (an MCAP file or a bag)
    image_topic : the topic ingest read images from (None: the first of
        :data:`~pipeline.io.mcap.DEFAULT_IMAGE_TOPICS` with an image message)
    indices : wanted frame indices, as ingest numbers frames
    n_images : how many images ingest read on the topic (``recording.json``);
        with the topic, it lets an indexed MCAP file be read through its index
        (:func:`pipeline.io.mcap_index.topic_messages`: only the chunks holding
        wanted frames), when the index counts as many; otherwise, or when the
        file has no usable index, the recording is streamed.

    Frames that cannot be decoded (or a file that ends early) are simply
    missing from the result; nothing raises for a damaged recording.
    """
    want = {int(i) for i in indices if int(i) >= 0}
    if not want:
        return {}
    found = None
    if image_topic is not None and n_images is not None:
        found = _indexed(path, image_topic, want, n_images)
    if found is None:
        found = _streamed(path, image_topic, want)
    out: dict[int, Frame] = {}
    for idx in sorted(found):
        frame = _frame(*found[idx])
        if frame is not None:
            out[idx] = frame
    return out


#: one image message: (schema name, message encoding, bytes)
_Raw = tuple[str, str, bytes]


def _frame(schema: str, enc: str, data: bytes) -> Frame | None:
    """A Frame of one image message, None when it does not decode."""
    try:
        em = decode_image_message(schema, enc, data)
    except Exception:  # noqa: BLE001 - an undecodable frame is just not shown
        return None
    media = {"png": "image/png", "jpeg": "image/jpeg", "jpg": "image/jpeg"}.get(
        em.encoding.lower(), ""
    )
    if em.kind == "compressed" and media:
        return Frame(em, bytes(em.data), media)
    try:  # a raw image is checked now (its pixels are what gets shown)
        frame = Frame(em)
        _ = frame.gray
    except Exception:  # noqa: BLE001 - an undecodable frame is just not shown
        return None
    return frame


def _indexed(path: Path, topic: str, want: set[int], n_images: int) -> dict[int, _Raw] | None:
    """The wanted image messages through the MCAP index, or None (stream instead)."""
    try:
        layout = locate(path)
    except Exception:  # noqa: BLE001 - unreachable recording: the stream says so
        return None
    if layout.read_by_rosbags:
        return None
    got = topic_messages(layout.files, topic, want, n_images)
    if got is None:
        return None
    return {k: (m.schema_name, m.message_encoding, m.data) for k, m in got.items()}


def _streamed(path: Path, image_topic: str | None, want: set[int]) -> dict[int, _Raw]:
    """The wanted image messages ``{frame index: message}``, streaming the recording.

    Frame indices are ranks in log-time order, ties in file order (as ingest
    numbers them): one pass when the image messages come in that order, which
    recorders write; a second pass for the right ones when they do not.
    """
    state = StreamState(path=str(path))
    topic = image_topic
    log_times: list[int] = []  # of every image message on the topic, in file order
    kept: dict[int, _Raw] = {}  # by position in the file
    try:
        for msg in iter_recording(locate(path), state):
            t, schema, enc = state.topic_type(msg.channel_id)
            if schema not in IMAGE_TYPES or (t != topic and topic is not None):
                continue
            if topic is None:
                if t not in DEFAULT_IMAGE_TOPICS:
                    continue
                topic = t
            if len(log_times) in want:
                kept[len(log_times)] = (schema, enc, msg.data)
            log_times.append(int(msg.log_time))
    except Exception:  # noqa: BLE001 - unreachable/damaged recording: what was read
        pass
    order = np.argsort(np.asarray(log_times, dtype=np.int64), kind="stable")
    if np.array_equal(order, np.arange(len(order))):
        return kept
    # out of log-time order: the file positions of the wanted ranks, in a second pass
    at = {int(order[r]): r for r in want if r < len(order)}
    state, pos, out = StreamState(path=str(path)), 0, {}
    try:
        for msg in iter_recording(locate(path), state):
            t, schema, enc = state.topic_type(msg.channel_id)
            if schema in IMAGE_TYPES and t == topic:
                if pos in at:
                    out[at[pos]] = (schema, enc, msg.data)
                pos += 1
    except Exception:  # noqa: BLE001 - unreachable/damaged recording: what was read
        pass
    return out


def grey_images(frames: dict[int, Frame], wanted: Iterable[int]) -> dict[int, np.ndarray]:
    """Grey images ``{frame index: (H, W) uint8}`` of the wanted frames that ``frames``
    holds (undecodable ones left out)."""
    out = {}
    for k in wanted:
        if k in frames:
            try:
                out[k] = frames[k].gray
            except Exception:  # noqa: BLE001 - an undecodable frame is just not shown
                continue
    return out


def recording_frames(data: RunData, indices: Iterable[int]) -> dict[int, Frame] | None:
    """The wanted frames of a run's recording (:func:`load_images` with the topic and
    image count ``recording.json`` holds); None when the recording is not reachable."""
    path = data.recording_path()
    if path is None:
        return None
    rec = data.recording or {}
    return load_images(path, rec.get("image_topic"), indices, rec.get("n_images"))


def _to_u8(g: np.ndarray) -> np.ndarray:
    if g.dtype == np.uint8:
        return np.ascontiguousarray(g)
    return np.ascontiguousarray((g.astype(np.float64) / 257.0).clip(0, 255).astype(np.uint8))


def ellipse_polyline(
    u: float, v: float, s: float, s_minor: float, angle: float, n: int = 72
) -> np.ndarray:
    """Points ``(n + 1, 2)`` (u, v) px of the fitted ellipse, closed.

    ``(u, v) + R(angle) [s/2 cos t, s_minor/2 sin t]``: ``s``, ``s_minor`` are
    the full axis lengths and ``angle`` the long-axis angle from ``+u`` towards
    ``+v`` (rad), as the detection stage writes them.
    """
    t = np.linspace(0.0, 2.0 * np.pi, n + 1)
    a, b = 0.5 * s, 0.5 * (s_minor if np.isfinite(s_minor) else s)
    th = angle if np.isfinite(angle) else 0.0
    c, si = np.cos(th), np.sin(th)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.stack([u + c * x - si * y, v + si * x + c * y], axis=1)


def annotate(
    gray: np.ndarray,
    ellipse: tuple[float, float, float, float, float] | None,
    designated: tuple[float, float] | None,
    width: int = 320,
) -> np.ndarray:
    """A BGR thumbnail ``width`` px wide with the fitted ellipse and the designated point.

    The ellipse (green) and its centre are drawn after scaling so lines stay
    one pixel wide; the designated pixel is a red cross.
    """
    h0, w0 = gray.shape[:2]
    k = width / float(w0)
    img = cv2.resize(gray, (width, max(1, round(h0 * k))), interpolation=cv2.INTER_AREA)
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)

    def px(p: np.ndarray) -> np.ndarray:
        # pixel-centre convention: centre of pixel i maps to (i + 0.5) k - 0.5
        return (p + 0.5) * k - 0.5

    if ellipse is not None and all(np.isfinite(ellipse[:3])):
        poly = px(ellipse_polyline(*ellipse))
        cv2.polylines(
            bgr, [np.round(poly * 16).astype(np.int32)], True, (60, 200, 60), 1, cv2.LINE_AA, 4
        )
        cu, cv_ = px(np.array(ellipse[:2]))
        cv2.circle(bgr, (round(cu), round(cv_)), 2, (60, 200, 60), -1, cv2.LINE_AA)
    if designated is not None and all(np.isfinite(designated)):
        du, dv = px(np.array(designated))
        p = (round(du), round(dv))
        cv2.drawMarker(bgr, p, (40, 40, 220), cv2.MARKER_CROSS, 12, 1, cv2.LINE_AA)
    return bgr


def png_data_uri(img: np.ndarray) -> str:
    """``data:image/png;base64,...`` of an image (deterministic encoder settings)."""
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:  # pragma: no cover - cv2 always encodes uint8 images
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def png_bytes(img: np.ndarray) -> bytes:
    """PNG bytes of an image (for Rerun's EncodedImage; a raw recording's frames).

    Every row "sub"-filtered (each byte minus the one to its left) and
    Huffman-coded at level 1, no string matching: on a 640 x 512 camera frame
    2.4 ms and 150 kB, against 5.2 ms and 142 kB with run-length coding and
    zlib's adaptive choice of filter per row, 28 ms and 159 kB at the default
    level 6 (the report writes 36-200 such). OpenCV before 4.11 cannot choose
    the filter: run-length coding then.
    """
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):
        params += [
            cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
            cv2.IMWRITE_PNG_FILTER,
            cv2.IMWRITE_PNG_FILTER_SUB,
        ]
    else:  # pragma: no cover - OpenCV < 4.11
        params += [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    ok, buf = cv2.imencode(".png", img, params)
    if not ok:  # pragma: no cover
        raise ValueError("PNG encoding failed")
    return bytes(buf.tobytes())
