"""Where a recording's bytes are: one file, or a rosbag2 bag directory of split files.

Kept free of numeric and MCAP imports: the run ledger hashes a recording
(:func:`recording_hash`) before deciding whether anything needs loading.
See :mod:`pipeline.io.recording` for the kinds and docs/ros-bags.md.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import BadInput


@dataclass(frozen=True)
class Layout:
    """Where a recording's bytes are.

    Attributes
    ----------
    path : what the user named (a file or a bag directory)
    kind : ``mcap``, ``rosbag2-mcap``, ``rosbag2-sqlite3`` or ``ros1``
    files : the data files, in reading order
    compression : a rosbag2 bag's ``compression_mode`` (``file``: every data file is
        zstd-compressed whole, ``NAME.mcap.zstd``; ``message``: each message's bytes
        are), ``""`` when not compressed
    """

    path: Path
    kind: str
    files: tuple[Path, ...]
    compression: str = ""

    @property
    def read_by_rosbags(self) -> bool:
        """Read through :mod:`pipeline.io.rosbags` (sqlite3, ROS 1 and compressed bags)."""
        return self.kind in ("rosbag2-sqlite3", "ros1") or bool(self.compression)


def locate(path: str | os.PathLike[str]) -> Layout:
    """The layout of a recording path.

    Raises
    ------
    BadInput
        Missing path; a directory without ``metadata.yaml``; a ``metadata.yaml``
        that does not parse or names missing files or an unknown storage.
    """
    p = Path(path)
    if p.name == "metadata.yaml" and p.is_file():
        p = p.parent
    if p.is_dir():
        return _bag_directory(p)
    if not p.is_file():
        raise BadInput(f"{p}: no such recording file or bag directory")
    if p.suffix == ".bag":
        kind = "ros1"
    elif p.suffix == ".db3":
        kind = "rosbag2-sqlite3"
    else:
        kind = "mcap"
    check_content(p, kind)
    return Layout(p, kind, (p,))


#: the first bytes of each kind of recording file, and what the kind is called
RECORDING_MAGIC = {
    "mcap": (b"\x89MCAP", "an MCAP file"),
    "ros1": (b"#ROSBAG V2.0", "a ROS 1 bag"),
    "rosbag2-sqlite3": (b"SQLite format 3\x00", "a rosbag2 SQLite file"),
}
#: what a file named so is expected to be
EXPECTED = {
    "mcap": "an MCAP recording or a ROS bag",
    "ros1": "a ROS 1 bag (#ROSBAG V2.0)",
    "rosbag2-sqlite3": "a rosbag2 .db3 file (SQLite)",
}
#: the first bytes of files often given by mistake, and what they are
OTHER_MAGIC = (
    (b"PK\x03\x04", "a ZIP archive"),
    (b"\x1f\x8b", "a gzip file"),
    (b"\x28\xb5\x2f\xfd", "a zstd-compressed file"),
    (b"BZh", "a bzip2 file"),
    (b"\x89PNG", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"%PDF", "a PDF document"),
    (b"PAR1", "a Parquet file"),
    (b"\x7fELF", "an executable"),
)


def check_content(path: Path, kind: str) -> None:
    """Refuse a recording file whose first bytes are not its kind's (an empty file, a
    CSV, an archive, a bag under an MCAP name), in one line naming what was expected and
    what was found: before any numeric library is imported (the refusal takes a blink,
    and the run folder is not made)."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError as exc:
        raise BadInput(f"{path}: cannot open: {exc.strerror}") from exc
    magic, name = RECORDING_MAGIC[kind]
    if head.startswith(magic):
        return
    expected = EXPECTED[kind]
    if size == 0:
        raise BadInput(f"{path}: not {name}: empty file (0 bytes); expected {expected}")
    for other, (m, other_name) in RECORDING_MAGIC.items():
        if other != kind and head.startswith(m):
            suffix = {"mcap": ".mcap", "ros1": ".bag", "rosbag2-sqlite3": ".db3"}[other]
            raise BadInput(
                f"{path}: not {name}: {other_name} by its content; name it {suffix} "
                f"(the file name says which reader is used)"
            )
    raise BadInput(f"{path}: not {name}: {_what_it_is(head, size)}; expected {expected}")


def _what_it_is(head: bytes, size: int) -> str:
    """A few words on a file from its first bytes."""
    for m, what in OTHER_MAGIC:
        if head.startswith(m):
            return f"{what} ({size} bytes)"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        text = ""
    if text and all(ch.isprintable() or ch in "\t\r\n" for ch in text):
        first = text.splitlines()[0] if text.strip() else text
        return f"text starting {first[:40]!r} ({size} bytes)"
    return f"{size} bytes starting {head[:8]!r}"


def _bag_directory(d: Path) -> Layout:
    meta = d / "metadata.yaml"
    if not meta.is_file():
        raise BadInput(
            f"{d}: a directory, but not a rosbag2 bag (no metadata.yaml); give an .mcap, "
            ".db3 or .bag file or a bag directory"
        )
    try:
        from ruamel.yaml import YAML

        info = YAML(typ="safe").load(meta.read_text())["rosbag2_bagfile_information"]
        storage = str(info["storage_identifier"])
        names = [str(x) for x in info["relative_file_paths"]]
        mode = str(info.get("compression_mode") or "").lower()
        fmt = str(info.get("compression_format") or "").lower()
    except Exception as exc:  # noqa: BLE001 - YAML errors, missing keys, wrong types
        raise BadInput(f"{meta}: not a readable rosbag2 metadata.yaml: {exc}") from exc
    files = tuple(d / Path(n).name for n in names)
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise BadInput(f"{meta}: lists bag file(s) {missing} that are not in {d}")
    if not files:
        raise BadInput(f"{meta}: lists no bag files (relative_file_paths is empty)")
    if storage not in ("mcap", "sqlite3"):
        raise BadInput(f"{meta}: storage_identifier {storage!r} is not mcap or sqlite3")
    mode = "" if mode == "none" else mode
    if mode and (mode not in ("file", "message") or fmt != "zstd"):
        raise BadInput(
            f"{meta}: compression {mode!r} / {fmt!r} is not readable "
            "(rosbag2 compresses with zstd, per file or per message)"
        )
    return Layout(d, f"rosbag2-{storage}", files, mode)


def recording_hash(layout: Layout) -> str:
    """SHA-256 (16 hex digits) of the recording's bytes.

    One file: the hash of its bytes (:func:`pipeline.io.fileio.file_hash`). A bag
    directory: the hash of its files' names and bytes in reading order.
    """
    from pipeline.io.fileio import file_hash

    if len(layout.files) == 1 and layout.kind != "rosbag2-mcap":
        return file_hash(layout.files[0])
    h = hashlib.sha256()
    for f in layout.files:
        h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:16]
