"""Both outputs of a run folder, ``report.html`` and ``run.rrd``, from one load.

:func:`pipeline.report.html.build_report` and :func:`pipeline.report.rrd.build_rrd`
each work alone (``vtcal report --no-rrd``); together they would each read the
artefacts and each stream the recording for images. Here the artefacts are
read once and the recording is read once, for the union of the frames
the two show (the thumbnails of rejected touch-ups, the last capture of every
touch-up). The files are the same as the two functions write alone.

The frames are read (and a raw frame encoded for run.rrd) in a second thread while
this one imports the Rerun SDK (0.2-0.3 s of Python imports): decompressing a
chunk and encoding a PNG release the GIL (docs/speed.md has the figures).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from pipeline.io.fileio import write_group
from pipeline.report.data import RunData, load_run
from pipeline.report.html import build_report, thumbnail_frames
from pipeline.report.images import Frame, grey_images, recording_frames
from pipeline.report.rrd import build_rrd
from pipeline.report.touchup_views import image_frames


def _read(
    data: RunData, thumbs: list[int], shots: list[int], have: dict[int, Frame]
) -> dict[int, Frame] | None:
    """The wanted frames (those in ``have`` are not read again), each shot's run.rrd bytes
    made (an undecodable one is left as it is: build_rrd meets it again and leaves it
    out); None without the recording."""
    missing = sorted({*thumbs, *shots} - have.keys())
    frames = dict(have)
    if missing:
        more = recording_frames(data, missing)
        if more is None:
            return None
        frames.update(more)
    _encode(frames, shots)
    return frames


def _encode(frames: dict[int, Frame], shots: list[int]) -> None:
    for k in shots:
        if k in frames:
            try:
                _ = frames[k].rrd_blob
            except Exception:  # noqa: BLE001 - an undecodable frame is just not shown
                continue


def prefetch_frames(run_dir: Path) -> dict[int, Frame]:
    """Every touch-up's last capture, read and encoded for run.rrd, before the report runs.

    Needs only ``touchups.parquet``, ``frames.parquet`` and ``recording.json`` (the
    touch-ups stage has run); :mod:`pipeline.report.warm` calls it while the later
    stages run and hands the frames to :func:`build_outputs`.
    """
    data = load_run(run_dir)
    shots = image_frames(data)
    frames = recording_frames(data, shots) or {}
    _encode(frames, shots)
    return frames


def build_outputs(
    run_dir: Path,
    tolerance_mm: float | None = None,
    *,
    html_path: Path | None = None,
    rrd_path: Path | None = None,
    frames: dict[int, Frame] | None = None,
) -> tuple[Path, Path]:
    """Write ``report.html`` and ``run.rrd`` of ``run_dir``; return their paths.

    Parameters
    ----------
    run_dir : the run folder
    tolerance_mm : the report's PASS/FAIL tolerance (default: run.json's, else the
        recording's key)
    html_path, rrd_path : destinations (default inside ``run_dir``)
    frames : frames already read (:func:`prefetch_frames`); only the others are read
    """
    run_dir = Path(run_dir)
    data = load_run(run_dir)
    thumbs, shots = thumbnail_frames(data), image_frames(data)
    with ThreadPoolExecutor(max_workers=1) as pool:
        reading = pool.submit(_read, data, thumbs, shots, frames or {})
        import pipeline.report.rrd_log  # noqa: F401 - the Rerun SDK, while the frames are read

        got = reading.result()
    with write_group():  # both fsync-ed at once, moved into place when both are made
        html = build_report(
            run_dir,
            html_path,
            tolerance_mm,
            data=data,
            images=None if got is None else grey_images(got, thumbs),
        )
        rrd = build_rrd(
            run_dir,
            rrd_path,
            data=data,
            images=None if got is None else {k: got[k] for k in shots if k in got},
        )
    return html, rrd
