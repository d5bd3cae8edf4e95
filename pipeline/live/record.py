"""The recording ``vtcal measure`` writes while it runs: crash-safe and resumable.

The file is the spec's MCAP (``recording.md``: ``/robot_description`` first,
``/joint_states``, ``/camera/image_raw``, metadata ``touchup``), written with
the project's one ROS 2 MCAP writer (:class:`pipeline.io.mcap_write.Recorder`).

**Crash-safe.** After every capture the chunk in progress is closed and the
file flushed to the operating system, so a killed process leaves a truncated
file that ``vtcal run`` reads up to the last whole chunk (it says the file was
truncated). After every finished touch-up the file is also ``fsync``-ed and a
small sidecar ``NAME.mcap.progress.json`` is replaced atomically: the plan's
hash, how many touch-ups are done, and the log time up to which the file holds
only finished touch-ups.

**Resumable.** Opened again on a partial file, the recording moves it aside
(``NAME.mcap.prev``), writes a new ``NAME.mcap`` with the messages of the
finished touch-ups copied from it (those logged up to the sidecar's
``safe_log_ns``; the interrupted touch-up is dropped), removes the old one and
carries on. One MCAP file per run, as the spec has it; a crash during the copy
leaves ``.prev`` in place and the next resume starts from it again.

Log times are the data's stamps (the cell clock), so a simulated cell's file
is in its simulated time like the simulator's own.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from pipeline.errors import BadInput
from pipeline.io import mcap as io_mcap
from pipeline.io.fileio import atomic_write_bytes
from pipeline.io.mcap_write import Recorder, stamp
from pipeline.live.protocols import Frame, JointReading
from pipeline.live.summary import METADATA_NAME

JOINT_TOPIC = "/joint_states"
IMAGE_TOPIC = "/camera/image_raw"
DESCRIPTION_TOPIC = "/robot_description"
PROGRESS_FORMAT = "vtcal-measure-progress"
#: chunk size: small, as a chunk is closed after every capture anyway
CHUNK_BYTES = 1 << 20


@dataclass
class Progress:
    """The sidecar: what of the plan the recording holds.

    Attributes
    ----------
    plan_sha256 : hash of the plan file the run follows
    n_plan : touch-ups in the plan
    t0_ns : log time of ``/robot_description``
    done : touch-ups finished (converged or given up), plan order
    safe_log_ns : every message up to this log time belongs to a finished touch-up
    touchups : one summary per finished touch-up (written by the caller)
    state : what the caller needs to go on (e.g. the image Jacobian)
    sessions : how many times the run was started
    finished : the recording is complete (footer written)
    """

    plan_sha256: str
    n_plan: int
    t0_ns: int
    done: int = 0
    safe_log_ns: int = 0
    touchups: list[dict[str, Any]] = field(default_factory=list)
    state: dict[str, Any] = field(default_factory=dict)
    sessions: int = 1
    finished: bool = False


def progress_path(path: Path) -> Path:
    """The sidecar of recording ``path``."""
    return path.with_name(path.name + ".progress.json")


def read_progress(path: Path) -> Progress | None:
    """The sidecar of ``path``, or None if there is none."""
    p = progress_path(path)
    if not p.exists():
        return None
    try:
        d = json.loads(p.read_text())
        if d.pop("format", None) != PROGRESS_FORMAT:
            raise ValueError("not a vtcal measure progress file")
        return Progress(**d)
    except (ValueError, TypeError) as exc:
        raise BadInput(f"{p}: unreadable progress file ({exc})") from None


def write_progress(path: Path, progress: Progress) -> None:
    """Replace the sidecar of ``path`` atomically."""
    data = {"format": PROGRESS_FORMAT, **asdict(progress)}
    atomic_write_bytes(progress_path(path), (json.dumps(data, indent=1) + "\n").encode())


class LiveRecording:
    """An MCAP recording written as the run goes (see the module doc).

    Use :func:`open_recording`; then :meth:`joints` and :meth:`image` as data
    arrive, :meth:`touchup_done` after each touch-up, :meth:`finish` at the end
    (or :meth:`abandon` on a fault: the file stays a readable truncated one).
    """

    def __init__(self, path: Path, progress: Progress) -> None:
        self.path = path
        self.progress = progress
        self._f: IO[bytes] = path.open("wb")
        self._rec = Recorder(self._f, chunk_size=CHUNK_BYTES)
        self._last_joint_ns = progress.t0_ns  # samples before the description are dropped
        self.n_joint_states = 0
        self.n_images = 0

    def describe(self, urdf: str, metadata: dict[str, str]) -> None:
        """Write ``/robot_description`` (log time ``t0_ns``) and the ``touchup`` metadata."""
        t0 = self.progress.t0_ns
        self._rec.push(t0, DESCRIPTION_TOPIC, "std_msgs/msg/String", {"data": urdf})
        self._rec.metadata("touchup", dict(metadata))
        self._sync(durable=False)

    def joints(self, names: list[str], samples: list[JointReading]) -> None:
        """Queue joint samples for ``/joint_states`` (older than the last one are dropped)."""
        for r in samples:
            t = int(r.stamp_ns)
            if t <= self._last_joint_ns:
                continue
            self._last_joint_ns = t
            msg = {
                "header": {"stamp": stamp(t), "frame_id": ""},
                "name": list(names),
                "position": [float(x) for x in r.positions],
                "velocity": [],
                "effort": [],
            }
            self._rec.push(t, JOINT_TOPIC, "sensor_msgs/msg/JointState", msg)
            self.n_joint_states += 1

    def image(self, frame: Frame) -> None:
        """Write one capture to ``/camera/image_raw`` and make it safe against a kill."""
        img = np.asarray(frame.image)
        if frame.encoding == "mono16":
            img = img.astype("<u2", copy=False)
        h, w = img.shape[:2]
        msg = {
            "header": {"stamp": stamp(frame.stamp_ns), "frame_id": "camera_optical_frame"},
            "height": h,
            "width": w,
            "encoding": frame.encoding,
            "is_bigendian": 0,
            "step": w * img.itemsize * (img.shape[2] if img.ndim == 3 else 1),
            "data": np.ascontiguousarray(img).tobytes(),
        }
        self._rec.push(int(frame.stamp_ns), IMAGE_TOPIC, "sensor_msgs/msg/Image", msg)
        self.n_images += 1
        self._sync(durable=False)

    def _sync(self, durable: bool) -> int:
        self._rec.cut_chunk()
        self._f.flush()
        if durable:
            os.fsync(self._f.fileno())
        return max(self._rec.last_log_time.values(), default=self.progress.t0_ns)

    def touchup_done(self, summary: dict[str, Any], state: dict[str, Any] | None = None) -> None:
        """Record that one more touch-up is finished: flush, fsync, then the sidecar."""
        self.progress.safe_log_ns = self._sync(durable=True)
        self.progress.done += 1
        self.progress.touchups.append(summary)
        if state is not None:
            self.progress.state = state
        write_progress(self.path, self.progress)

    def finish(self, measurement: dict[str, str] | None = None) -> None:
        """Write the summary and footer; mark the sidecar finished.

        ``measurement``: the string map of :func:`pipeline.live.summary.as_metadata`,
        written as the metadata record ``measurement`` (how the recording was measured).
        """
        if measurement:
            self._rec.metadata(METADATA_NAME, dict(measurement))
        self._rec.finish()
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        self.progress.finished = True
        write_progress(self.path, self.progress)

    def abandon(self) -> None:
        """Close after a fault: what was flushed stays readable, the run can resume."""
        try:
            self._sync(durable=True)
        finally:
            self._f.close()

    def copy_from(self, old: Path, until_log_ns: int) -> None:
        """Copy the joint states and images of ``old`` logged up to ``until_log_ns``."""
        state = io_mcap.StreamState(str(old))
        for m in io_mcap.iter_messages(old, state):
            if m.log_time > until_log_ns:
                continue
            topic, sname, menc = state.topic_type(m.channel_id)
            if topic == JOINT_TOPIC:
                t, names, pos = io_mcap.decode_joint_state(bytes(m.data))
                self.joints(names, [JointReading(pos, t)])
            elif topic == IMAGE_TOPIC and sname in io_mcap.IMAGE_TYPES:
                e = io_mcap.decode_image_message(sname, menc, bytes(m.data))
                self._copy_image(e, m.log_time)
        self._sync(durable=True)

    def _copy_image(self, e: io_mcap.EncodedImage, log_ns: int) -> None:
        msg = {
            "header": {"stamp": stamp(e.stamp_ns), "frame_id": "camera_optical_frame"},
            "height": e.height,
            "width": e.width,
            "encoding": e.encoding,
            "is_bigendian": int(e.bigendian),
            "step": e.step,
            "data": bytes(e.data),
        }
        self._rec.push(log_ns, IMAGE_TOPIC, "sensor_msgs/msg/Image", msg)
        self.n_images += 1


def open_recording(
    path: Path,
    urdf: str,
    metadata: dict[str, str],
    plan_sha256: str,
    n_plan: int,
    t0_ns: int,
) -> LiveRecording:
    """Start recording ``path``, or resume the partial recording there.

    Raises
    ------
    BadInput
        ``path`` exists but is no partial ``vtcal measure`` recording, is already
        complete, or was measured with another plan.
    """
    path = Path(path)
    prev = path.with_name(path.name + ".prev")
    progress = read_progress(path)
    if progress is not None and progress.done == 0 and not path.exists() and not prev.exists():
        progress = None  # killed between writing the sidecar and creating the file
    if progress is None:
        if path.exists() or prev.exists():
            raise BadInput(
                f"{path}: exists and has no {progress_path(path).name}: not a partial "
                "vtcal measure recording; remove it or choose another --out"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        progress = Progress(plan_sha256=plan_sha256, n_plan=n_plan, t0_ns=t0_ns)
        progress.safe_log_ns = t0_ns
        write_progress(path, progress)
        rec = LiveRecording(path, progress)
        rec.describe(urdf, metadata)
        return rec
    if progress.finished:
        raise BadInput(
            f"{path}: already complete ({progress.done} of {progress.n_plan} touch-ups); "
            "remove it to measure again"
        )
    if progress.plan_sha256 != plan_sha256:
        raise BadInput(
            f"{path}: was measured with another plan (sha256 {progress.plan_sha256[:12]}...); "
            "resume with the same --plan or choose another --out"
        )
    if not prev.exists():
        if not path.exists():
            raise BadInput(
                f"{path}: missing, but {progress_path(path).name} says {progress.done} "
                "touch-ups were recorded; remove the progress file to start again"
            )
        os.replace(path, prev)
    progress.sessions += 1
    rec = LiveRecording(path, progress)
    rec.describe(urdf, metadata)
    rec.copy_from(prev, progress.safe_log_ns)
    write_progress(path, progress)
    prev.unlink()
    return rec
