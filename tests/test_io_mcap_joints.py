"""Joint-state decoding: the repeated-layout fast path reads what was written (io_mcap)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from pipeline.io import mcap as io_mcap
from pipeline.io.mcap import decode_joint_state


def encode(stamp_ns, frame, names, pos, order="<", xcdr2=False, vel=()):
    """``sensor_msgs/JointState`` as CDR (XCDR1: 8-byte values aligned to 8; XCDR2: to 4)."""
    rep = (0x0006 if xcdr2 else 0x0000) | (1 if order == "<" else 0)
    out = bytearray(struct.pack(">H", rep) + b"\0\0")
    a8 = 4 if xcdr2 else 8

    def align(n):
        out.extend(b"\0" * (-(len(out) - 4) % n))

    def u32(v):
        align(4)
        out.extend(struct.pack(order + "I", v))

    def string(t):
        raw = t.encode() + b"\0"
        u32(len(raw))
        out.extend(raw)

    def f64s(xs):
        u32(len(xs))
        if len(xs):
            align(a8)
        out.extend(struct.pack(order + f"{len(xs)}d", *xs))

    align(4)
    out.extend(struct.pack(order + "iI", stamp_ns // 10**9, stamp_ns % 10**9))
    string(frame)
    u32(len(names))
    for n in names:
        string(n)
    f64s(pos)
    f64s(vel)
    f64s(())
    return bytes(out)


J6 = [f"joint_{i}" for i in range(1, 7)]


def test_every_layout_in_a_stream_reads_what_was_written():
    """Runs of one layout (the fast path) interleaved with changes of each part of it."""
    rng = np.random.default_rng(3)
    layouts = [
        ("", J6, "<", False),
        ("base", J6, "<", False),  # frame id: names shift by 4 bytes
        ("", J6[:5], "<", False),  # fewer names
        ("", [n + "x" for n in J6], "<", False),  # other names, same count
        ("", J6, ">", False),  # big-endian
        ("ab", J6, "<", True),  # XCDR2: positions aligned to 4
        ("", ["a"], "<", False),
    ]
    io_mcap._JOINT_LAYOUT[0] = None
    for frame, names, order, xcdr2 in [*layouts, *layouts[::-1]]:
        for _ in range(3):
            stamp = int(rng.integers(0, 2**60))
            pos = rng.normal(size=len(names))
            vel = rng.normal(size=len(names)) if rng.random() < 0.5 else ()
            got = decode_joint_state(encode(stamp, frame, names, pos, order, xcdr2, vel))
            assert got[0] == stamp and got[1] == names
            assert got[2].dtype == np.float64 and np.array_equal(got[2], pos)


def test_a_message_cut_short_still_fails():
    good = encode(5, "", J6, np.arange(6.0))
    io_mcap._JOINT_LAYOUT[0] = None
    decode_joint_state(good)
    with pytest.raises(ValueError):
        decode_joint_state(good[: len(good) - 28])  # the positions cut


def test_zero_positions_with_names_is_read_as_zero():
    io_mcap._JOINT_LAYOUT[0] = None
    for _ in range(2):
        got = decode_joint_state(encode(7, "", J6, ()))
        assert got[1] == J6 and got[2].shape == (0,)
