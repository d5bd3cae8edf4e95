"""``run.rrd``: the Rerun recording of a run, for 3-D inspection.

Built only from the artefacts of a run folder (like the HTML report). Entity
tree (base frame = ``world``, z up, metres)::

    world/robot/nominal          LineStrips3D  skeleton of the nominal robot at the pose
    world/robot/calibrated       LineStrips3D  skeleton of the calibrated robot
    world/robot/calibrated/flange            Transform3D  T_base_flange (calibrated)
    world/robot/calibrated/flange/pin        Points3D     virtual pin (flange frame)
    world/robot/calibrated/flange/camera     Transform3D  nominal camera mount (a guess)
    world/robot/calibrated/flange/camera/image  Pinhole + EncodedImage + ellipse + designated point
    world/targets                Points3D      identified target centres (static)
    world/pins                   Points3D      calibrated pin at every used touch-up (static)
    world/residuals_xS           Arrows3D      target -> pin, lengths scaled by S (static)
    world/rejected               Points3D      rejected touch-ups, labelled with the reason
    convergence/du|dv|ds         Scalars       |e_T| components per capture, px
    log/rejected                 TextLog       one line per rejected touch-up
    notes                        TextDocument  what is shown and what is guessed

Timelines: ``touchup`` (sequence: the touch-up id; poses, images, rejected
marks), ``stamp`` (the touch-up's last capture stamp, same rows) and
``iteration`` (capture number within a touch-up, for the convergence
series). A default blueprint shows the 3-D scene, the camera image and the
convergence plots side by side. Nothing wall-clock is logged (the
``log_time`` timeline is disabled), and the recording id is
:func:`pipeline.report.data.run_uuid` of the folder's artefacts, so the same
folder gives the same recording.

The camera intrinsics and mount are unknown to the pipeline (the method never
needs them). The frustum is a nominal guess: the camera sits at the flange
origin looking at the virtual pin, with focal length ``f = s0 d / D`` from
eq. (1) of the seed paper (``s0`` the designated size, ``d`` the pin
stand-off, ``D`` the target diameter). The notes say so.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.io.fileio import commit_file
from pipeline.io.run_folder import RUN_FILES
from pipeline.report.data import RunData, load_run, run_uuid
from pipeline.report.images import Frame

APP_ID = "vtcal"


def build_rrd(
    run_dir: Path,
    out_path: Path | None = None,
    recording_id: str | None = None,
    *,
    data: RunData | None = None,
    images: dict[int, Frame] | None = None,
) -> Path:
    """Write ``run.rrd`` of a run folder from its artefacts; return its path.

    Parameters
    ----------
    run_dir : the run folder
    out_path : destination (default ``run_dir / RUN_FILES["rrd"]``)
    recording_id : Rerun recording id (default :func:`run_uuid` of the folder,
        so the same artefacts always give the same id)
    data, images : the run folder already loaded (:func:`load_run`) and the camera
        images (:func:`image_frames`; None: not reachable), when the caller has them

    The file is written to a temporary sibling, finalised by
    ``RecordingStream.disconnect()`` and then moved into place.
    """
    run_dir = Path(run_dir)
    out = Path(out_path) if out_path is not None else run_dir / RUN_FILES["rrd"]
    loaded = data is not None
    data = data if data is not None else load_run(run_dir)
    rid = recording_id or run_uuid(run_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial")
    import rerun as rr  # here, not at import: the report's code key imports this module

    from pipeline.report.rrd_log import log_run

    rec = rr.RecordingStream(APP_ID, recording_id=rid, send_properties=False)
    rec.set_log_time_enabled(False)
    rec.save(str(tmp))
    try:
        try:
            log_run(rec, data, images, loaded)
        finally:
            rec.disconnect()  # finalises the file (flush alone does not)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    # fsync-ed and moved into place as it is (not read back and copied: 11 MB on the
    # 72-touch-up cell); inside a write group, when the group ends
    commit_file(tmp, out, 0o644)
    return out
