"""The line format of the vtcal cell protocol (docs/measure.md, "The cell protocol").

Shared by the client (:mod:`pipeline.live.tcp_robot`) and the reference
server (:mod:`pipeline.live.tcp_server`). Every request is one ASCII line
``COMMAND arg ...`` ending in ``\\n``; every reply is one line, ``OK field ...``
or ``ERR kind message``. A few replies are followed by a block of bytes whose
length is the last field of the ``OK`` line: ``CAPTURE`` (``OK FRAME stamp_ns
encoding width height nbytes``, then raw pixels, row-major, no padding,
little-endian for ``mono16``), ``JOINTLOG?`` (``OK nbytes``, then lines
``stamp_ns q1 ... qn``), ``URDF?`` and ``META?`` (``OK nbytes``, then UTF-8 text).
Numbers are decimal text; floats as Python's ``repr`` writes them (they read
back bit-identical), stamps as integer nanoseconds.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pipeline.live.protocols import ENCODINGS, FAULT_KINDS, Frame, MeasureFault

#: what a server answers to ``HELLO``: the protocol's name and version
PROTOCOL = "vtcal-cell"
VERSION = 1

#: the commands a controller program must answer (docs/measure.md)
REQUIRED = ("HELLO", "NAMES?", "JOINTS?", "MOVEJ", "MOVEL_FLANGE", "STILL?")
#: the ones it may answer with ``ERR unsupported``; the client then falls back
OPTIONAL = ("WAIT", "JOINTLOG?", "CAPTURE", "URDF?", "META?", "BYE")

#: the kind a server names for a command it does not implement
UNSUPPORTED = "unsupported"

#: bytes per pixel of each image encoding
PIXEL_BYTES = {"mono8": 1, "mono16": 2, "rgb8": 3, "bgr8": 3}


class Unsupported(Exception):
    """The server answered ``ERR unsupported``: an optional command it lacks."""


def floats(values: Iterable[float]) -> str:
    """Space-separated ``repr`` of each value (round-trips a float64 exactly)."""
    return " ".join(repr(float(v)) for v in values)


def parse_floats(fields: list[str], what: str) -> np.ndarray:
    """Floats of ``fields``; a field that is not a number is a connection fault."""
    try:
        return np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise MeasureFault("connection", f"{what}: expected numbers, got {fields!r}") from None


def error_line(kind: str, message: str) -> str:
    """The ``ERR`` reply of a fault (newlines in ``message`` flattened)."""
    return f"ERR {kind} {' '.join(message.split())}"


def raise_error(line: str, command: str) -> None:
    """Raise what an ``ERR kind message`` reply to ``command`` means.

    Raises
    ------
    Unsupported
        ``kind`` is ``unsupported``.
    MeasureFault
        ``kind`` is one of :data:`~pipeline.live.protocols.FAULT_KINDS`; any
        other kind is reported as a ``connection`` fault naming it.
    """
    _, _, rest = line.partition(" ")
    kind, _, message = rest.partition(" ")
    if kind == UNSUPPORTED:
        raise Unsupported(f"{command}: {message}")
    if kind in FAULT_KINDS:
        raise MeasureFault(kind, f"{command}: {message}")
    raise MeasureFault("connection", f"{command}: unknown error kind {kind!r}: {message}")


def frame_header(frame: Frame) -> str:
    """The reply line announcing ``frame``'s pixels."""
    img = np.asarray(frame.image)
    h, w = img.shape[:2]
    return f"OK FRAME {int(frame.stamp_ns)} {frame.encoding} {w} {h} {img.nbytes}"


def frame_payload(frame: Frame) -> bytes:
    """The pixels of ``frame`` as the protocol sends them (row-major, little-endian)."""
    img = np.asarray(frame.image)
    if frame.encoding == "mono16":
        img = img.astype("<u2", copy=False)
    return np.ascontiguousarray(img).tobytes()


def parse_frame_header(fields: list[str]) -> tuple[int, str, int, int, int]:
    """``(stamp_ns, encoding, width, height, nbytes)`` of a ``FRAME`` reply's fields."""
    if len(fields) != 6 or fields[0] != "FRAME":
        raise MeasureFault("connection", f"CAPTURE: expected 'OK FRAME ...', got {fields!r}")
    try:
        stamp, w, h, n = int(fields[1]), int(fields[3]), int(fields[4]), int(fields[5])
    except ValueError:
        raise MeasureFault("connection", f"CAPTURE: bad FRAME fields {fields!r}") from None
    enc = fields[2]
    if enc not in ENCODINGS:
        raise MeasureFault("connection", f"CAPTURE: encoding {enc!r} not one of {ENCODINGS}")
    if w <= 0 or h <= 0 or n != w * h * PIXEL_BYTES[enc]:
        raise MeasureFault("connection", f"CAPTURE: {w}x{h} {enc} cannot hold {n} bytes")
    return stamp, enc, w, h, n


def decode_frame(stamp_ns: int, encoding: str, width: int, height: int, data: bytes) -> Frame:
    """The :class:`Frame` of a ``FRAME`` reply and its pixel bytes."""
    dtype = "<u2" if encoding == "mono16" else "u1"
    img = np.frombuffer(data, dtype=dtype)
    shape = (height, width, 3) if PIXEL_BYTES[encoding] == 3 else (height, width)
    return Frame(
        image=img.reshape(shape).astype(dtype[-2:], copy=True), stamp_ns=stamp_ns, encoding=encoding
    )
