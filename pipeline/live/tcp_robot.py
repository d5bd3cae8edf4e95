"""The client side of the vtcal cell protocol: a :class:`Robot` and a :class:`Camera` over TCP.

A controller program (URScript, RAPID, KRL, Karel, a ROS 2 node, or the
reference server :mod:`pipeline.live.tcp_server`) listens on a TCP port and
answers the line commands of :mod:`pipeline.live.wire`; vtcal imports no
vendor SDK. docs/measure.md, "The cell protocol", is the reference.

Joint states for the recording come from ``JOINTLOG?`` when the server answers
it (samples the controller logged, on its own clock) and otherwise from a
:class:`~pipeline.live.joint_poller.JointPoller` reading ``JOINTS?`` at
100 Hz over a second connection (so polling goes on while a move blocks the
first one).
"""

from __future__ import annotations

import socket
import threading
import time
from urllib.parse import urlsplit

import numpy as np

from pipeline.live import wire
from pipeline.live.joint_poller import JointPoller
from pipeline.live.protocols import F64, Frame, JointReading, MeasureFault

#: seconds a query (everything but a move or a capture) may take
QUERY_TIMEOUT_S = 5.0
#: seconds a move may take before the link is declared lost
MOVE_TIMEOUT_S = 300.0


def parse_address(url: str) -> tuple[str, int]:
    """``(host, port)`` of ``tcp://HOST:PORT``; a bad address is a ``connection`` fault."""
    parts = urlsplit(url if "://" in url else f"tcp://{url}")
    if parts.scheme != "tcp" or not parts.hostname or parts.port is None:
        raise MeasureFault("connection", f"{url}: expected tcp://HOST:PORT")
    return parts.hostname, parts.port


class TcpLink:
    """One connection: send a line, read the reply; every failure is a ``connection`` fault."""

    def __init__(self, url: str, timeout_s: float = QUERY_TIMEOUT_S) -> None:
        self.url = url
        host, port = parse_address(url)
        self.timeout_s = timeout_s
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            raise MeasureFault("connection", f"{url}: cannot connect ({exc})") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._rfile = self._sock.makefile("rb")
        self._lock = threading.Lock()

    def _lost(self, command: str, why: str) -> MeasureFault:
        return MeasureFault("connection", f"{self.url}: {command}: {why}")

    def request(self, line: str, timeout_s: float | None = None) -> list[str]:
        """Send ``line``; return the fields after ``OK`` (raise on ``ERR``)."""
        with self._lock:
            return self._request(line, timeout_s)

    def _request(self, line: str, timeout_s: float | None) -> list[str]:
        command = line.split(" ", 1)[0]
        try:
            self._sock.settimeout(timeout_s or self.timeout_s)
            self._sock.sendall(line.encode("ascii") + b"\n")
            reply = self._rfile.readline()
        except TimeoutError:
            raise self._lost(
                command, f"no reply within {timeout_s or self.timeout_s:g} s"
            ) from None
        except OSError as exc:
            raise self._lost(command, f"connection lost ({exc})") from None
        if not reply.endswith(b"\n"):
            raise self._lost(command, "connection closed by the cell")
        text = reply.decode("ascii", "replace").strip()
        if text.startswith("ERR"):
            wire.raise_error(text, command)
        if text != "OK" and not text.startswith("OK "):
            raise self._lost(command, f"unexpected reply {text[:80]!r}")
        return text.split()[1:]

    def request_bytes(self, line: str, timeout_s: float) -> tuple[list[str], bytes]:
        """Send ``line``; return the ``OK`` fields and the ``nbytes`` (last field) after them."""
        with self._lock:
            fields = self._request(line, timeout_s)
            try:
                n = int(fields[-1])
                data = self._rfile.read(n)
            except (ValueError, IndexError):
                raise self._lost(line, f"reply {fields!r} lacks a byte count") from None
            except OSError as exc:
                raise self._lost(line, f"connection lost ({exc})") from None
            if len(data) != n:
                raise self._lost(line, f"connection closed after {len(data)} of {n} bytes")
            return fields, data

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:
            pass


class TcpRobot:
    """:class:`~pipeline.live.protocols.Robot` over the cell protocol.

    Parameters
    ----------
    url : ``tcp://HOST:PORT``
    timeout_s : seconds a query may take
    move_timeout_s : seconds a move (``MOVEJ``, ``MOVEL_FLANGE``, ``WAIT``) may take
    poll_hz : rate of the ``JOINTS?`` poller used when the server lacks ``JOINTLOG?``
    host_clock : poll ``JOINTS?`` even if the server has ``JOINTLOG?`` and stamp the
        samples with the host clock (the middle of the request), the clock the
        OpenCV and folder cameras stamp images with; for a cell whose camera is
        not served over this link and whose controller clock is not synchronised
    """

    def __init__(
        self,
        url: str,
        timeout_s: float = QUERY_TIMEOUT_S,
        move_timeout_s: float = MOVE_TIMEOUT_S,
        poll_hz: float = 100.0,
        host_clock: bool = False,
    ) -> None:
        self.url = url
        self.link = TcpLink(url, timeout_s)
        self.move_timeout_s = move_timeout_s
        self._poll_hz = poll_hz
        self.host_clock = host_clock
        hello = self.link.request("HELLO")
        if not hello or hello[0] != wire.PROTOCOL:
            self.link.close()
            raise MeasureFault("connection", f"{url}: not a {wire.PROTOCOL} server ({hello!r})")
        self._names = self.link.request("NAMES?")
        if not self._names:
            raise MeasureFault("connection", f"{url}: NAMES? named no joints")
        self._has_wait = True
        self._poller: JointPoller | None = None
        self._poll_link: TcpLink | None = None
        self._log_since = self.read_joints().stamp_ns
        self._has_log = False
        if not host_clock:
            try:
                self.link.request_bytes(f"JOINTLOG? {self._log_since}", timeout_s)
                self._has_log = True
            except wire.Unsupported:
                pass
        if not self._has_log:
            self._poll_link = TcpLink(url, timeout_s)
            self._poller = JointPoller(self._poll_read, poll_hz)

    @property
    def joint_names(self) -> list[str]:
        return list(self._names)

    @property
    def joint_source(self) -> str:
        """``JOINTLOG?`` (the controller's own samples) or ``poller`` (``JOINTS?`` at poll_hz)."""
        if self._has_log:
            return "JOINTLOG?"
        return f"poller {self._poll_hz:g} Hz" + (", host clock" if self.host_clock else "")

    def _reading(self, fields: list[str], what: str) -> JointReading:
        if len(fields) != 1 + len(self._names):
            raise MeasureFault(
                "connection",
                f"{self.url}: {what}: expected a stamp and {len(self._names)} positions, "
                f"got {len(fields)} fields",
            )
        try:
            stamp = int(fields[0])
        except ValueError:
            raise MeasureFault(
                "connection", f"{self.url}: {what}: bad stamp {fields[0]!r}"
            ) from None
        return JointReading(positions=wire.parse_floats(fields[1:], what), stamp_ns=stamp)

    def read_joints(self) -> JointReading:
        return self._reading(self.link.request("JOINTS?"), "JOINTS?")

    def _poll_read(self) -> JointReading:
        assert self._poll_link is not None
        t0 = time.time_ns()
        r = self._reading(self._poll_link.request("JOINTS?"), "JOINTS?")
        if self.host_clock:
            return JointReading(r.positions, (t0 + time.time_ns()) // 2)
        return r

    def move_joints(self, q: F64, speed: float) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape != (len(self._names),):
            raise ValueError(f"MOVEJ needs {len(self._names)} positions, got shape {q.shape}")
        self.link.request(f"MOVEJ {wire.floats(q)} {float(speed)!r}", self.move_timeout_s)

    def move_flange(self, dp_flange_m: F64) -> None:
        dp = np.asarray(dp_flange_m, dtype=float).reshape(3)
        self.link.request(f"MOVEL_FLANGE {wire.floats(dp)}", self.move_timeout_s)

    def is_still(self) -> bool:
        fields = self.link.request("STILL?")
        if fields not in (["0"], ["1"]):
            raise MeasureFault("connection", f"{self.url}: STILL?: expected 0 or 1, got {fields!r}")
        return fields == ["1"]

    def wait(self, seconds: float) -> None:
        if self._has_wait:
            try:
                self.link.request(f"WAIT {float(seconds)!r}", self.move_timeout_s + seconds)
                return
            except wire.Unsupported:
                self._has_wait = False
        time.sleep(seconds)

    def fetch_urdf(self) -> str | None:
        """The controller's nominal URDF (``URDF?``), or None if it does not serve one."""
        try:
            return self.link.request_bytes("URDF?", self.link.timeout_s)[1].decode("utf-8")
        except wire.Unsupported:
            return None

    def fetch_metadata(self) -> dict[str, str]:
        """The ``touchup`` metadata keys the cell serves (``META?``); empty if none."""
        try:
            data = self.link.request_bytes("META?", self.link.timeout_s)[1].decode("utf-8")
        except wire.Unsupported:
            return {}
        out = {}
        for line in data.splitlines():
            k, sep, v = line.partition("=")
            if sep and k.strip():
                out[k.strip()] = v.strip()
        return out

    def drain_joints(self) -> list[JointReading]:
        """Joint samples since the last call, in stamp order (for ``/joint_states``)."""
        if self._poller is not None:
            return self._poller.drain()
        fields, data = self.link.request_bytes(f"JOINTLOG? {self._log_since}", self.link.timeout_s)
        out = []
        for line in data.decode("ascii", "replace").splitlines():
            if line.strip():
                out.append(self._reading(line.split(), "JOINTLOG?"))
        if out:
            self._log_since = out[-1].stamp_ns
        return out

    def close(self) -> None:
        """Say goodbye (if the server listens) and close both connections."""
        if self._poller is not None:
            self._poller.stop()
        for link in (self.link, self._poll_link):
            if link is None:
                continue
            try:
                link.request("BYE", 1.0)
            except (MeasureFault, wire.Unsupported):
                pass
            link.close()


class TcpCamera:
    """:class:`~pipeline.live.protocols.Camera` over the cell protocol's ``CAPTURE``.

    Shares the robot's connection when given it (one link for a cell whose
    controller also serves the camera).
    """

    def __init__(self, link: TcpLink, timeout_s: float = 10.0) -> None:
        self.link = link
        self.timeout_s = timeout_s

    def capture(self) -> Frame:
        try:
            fields, data = self.link.request_bytes("CAPTURE", self.timeout_s)
        except wire.Unsupported:
            raise MeasureFault(
                "connection", f"{self.link.url}: the cell serves no camera (CAPTURE unsupported)"
            ) from None
        stamp, enc, w, h, _ = wire.parse_frame_header(fields)
        return wire.decode_frame(stamp, enc, w, h, data)
