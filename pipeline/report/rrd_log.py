"""Logging a run into an open Rerun recording stream (what ``run.rrd`` holds).

The entity tree, timelines and notes are described in :mod:`pipeline.report.rrd`,
which opens and finalises the file; this module is the part that needs the
Rerun SDK (0.2-0.3 s of imports). It is apart so that the report's code key
(:mod:`pipeline.run.code_key`, which imports the stage's entry modules) does not load
the SDK. The warm report process (:mod:`pipeline.report.warm`) imports it while
the run ingests; without that process the report stage imports it while its
frames are read (:mod:`pipeline.report.outputs`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
import rerun as rr
import rerun.blueprint as rrb

from pipeline.kinematics.chain import Chain, fk
from pipeline.measurement.image import focal_from_size
from pipeline.report.data import RunData
from pipeline.report.figures import pin_positions, skeleton_points, target_positions
from pipeline.report.images import Frame, ellipse_polyline, recording_frames
from pipeline.report.touchup_views import (
    convergence_traces,
    designated,
    detection_ellipse,
    image_frames,
    touchup_frames,
)

CAMERA = "world/robot/calibrated/flange/camera"
#: residual arrows are drawn this many times their length
RESIDUAL_SCALE = 100
GREY = (150, 150, 160)
BLUE = (31, 111, 235)
RED = (209, 36, 47)
GREEN = (45, 164, 78)
ORANGE = (227, 98, 9)
#: vtcal puts pixel centres at integers, Rerun's image space at half-integers
#: (the image spans [0, W] x [0, H]): 2-D overlays are shifted by half a pixel
PX = 0.5


def camera_guess(
    data: RunData, p_flange_pin: np.ndarray | None
) -> tuple[np.ndarray, float, tuple[int, int]] | None:
    """Nominal camera: ``(T_flange_camera (4,4), focal px, (width, height))`` or None.

    The camera frame (x right, y down, z optical axis, as OpenCV) sits at the
    flange origin with its z axis towards the virtual pin; the focal length
    is ``f = s0 d / D`` (:func:`pipeline.measurement.image.focal_from_size`, with
    ``d = |p_flange_pin|``); the
    image size is ``2 * designated + 1`` (designated pixel at the centre).
    """
    d0 = designated(data)
    if p_flange_pin is None or d0 is None:
        return None
    d = float(np.linalg.norm(p_flange_pin))
    if d <= 0:
        return None
    try:
        D = float(data.meta.get("target_diameter_m", "nan"))
    except ValueError:
        D = float("nan")
    s0 = d0[2]
    f = (
        focal_from_size(s0, d, D)
        if np.isfinite(D) and D > 0 and np.isfinite(s0)
        else 2.0 * (d0[0] + 0.5)
    )
    z = p_flange_pin / d
    x = np.cross([0.0, 1.0, 0.0], z) if abs(z[1]) < 0.9 else np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    size = (int(round(2 * d0[0] + 1)), int(round(2 * d0[1] + 1)))
    return T, f, size


def log_run(
    rec: rr.RecordingStream,
    data: RunData,
    images: dict[int, Frame] | None = None,
    loaded: bool = False,
) -> list[str]:
    """Log everything of a run into an open recording stream; return notes (what was skipped).

    ``images`` are the camera images when ``loaded`` (already read from the
    recording, :func:`image_frames`); else they are read here. In order: the static
    scene (:func:`_log_targets`, :func:`_log_pins`), the nominal camera and the
    pin, the touch-up poses (:func:`_log_pose_columns`) and images
    (:func:`_log_images`), the convergence series, the notes.
    """
    notes: list[str] = []
    rec.send_blueprint(_blueprint())
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    tu = data.touchup_table()
    nominal = data.nominal_chain()
    calibrated = data.calibrated_chain()
    p_pin = data.p_flange_pin()
    targets = target_positions(data)

    # ---------------------------------------------------------------- static
    if targets:
        _log_targets(rec, targets)
    else:
        notes.append("targets: not available (no targets.parquet)")
    if tu is None:
        notes.append("touch-ups: not available")
        _notes(rec, data, notes, None)
        return notes
    inl = tu["inlier"].astype(bool).to_numpy() if "inlier" in tu else np.ones(len(tu), bool)
    pins = pin_positions(data, tu)
    if pins is not None:
        _log_pins(rec, tu, inl, pins, targets)
    else:
        notes.append("calibrated robot: not available (no calibrated.urdf with a virtual_pin)")

    # ------------------------------------------------------- per touch-up pose
    q = data.joint_matrix(tu)
    cam = camera_guess(data, p_pin)
    if cam is None:
        notes.append("camera frustum: not shown (no virtual pin or no designated pixel)")
    frames = touchup_frames(data)
    if not loaded:
        images = _images(data)
    if images is None:
        notes.append("images: not shown (the recording in recording.json is not reachable)")
    d0 = designated(data)
    if q is not None:
        if cam is not None:
            _log_camera(rec, cam, images, d0, p_pin)
        if p_pin is not None:
            rec.log(
                "world/robot/calibrated/flange/pin",
                rr.Points3D([p_pin], radii=0.003, colors=[ORANGE], labels=["virtual pin"]),
                static=True,
            )
        when = _Timelines(tu)
        drawn = np.flatnonzero(np.all(np.isfinite(q), axis=1))  # rows with a joint vector
        _log_pose_columns(rec, tu, inl, when, drawn, q, nominal, calibrated, p_pin)
        _log_images(rec, data, when, drawn, frames, images or {}, d0)
    else:
        notes.append("robot poses: not available (no joint columns or no URDF)")

    # ------------------------------------------------------------ convergence
    traces = convergence_traces(data)
    if traces:
        for tid in sorted(traces):
            tr = np.abs(traces[tid])
            seq = np.arange(len(tr), dtype=np.int64)
            for k, name in enumerate(("du", "dv", "ds")):
                rec.send_columns(
                    f"convergence/{name}/touchup_{tid:04d}",
                    indexes=[rr.TimeColumn("iteration", sequence=seq)],
                    columns=rr.Scalars.columns(scalars=tr[:, k]),
                )
    else:
        notes.append("e_T convergence: not available")
    _notes(rec, data, notes, cam)
    return notes


def _log_targets(rec: rr.RecordingStream, targets: dict[int, np.ndarray]) -> None:
    """The identified target centres (static)."""
    ids = sorted(targets)
    rec.log(
        "world/targets",
        rr.Points3D(
            np.array([targets[k] for k in ids]),
            radii=0.004,
            colors=[GREEN] * len(ids),
            labels=[f"target {k}" for k in ids],
            show_labels=True,
        ),
        static=True,
    )


def _log_pins(
    rec: rr.RecordingStream,
    tu: pd.DataFrame,
    inl: np.ndarray,
    pins: np.ndarray,
    targets: dict[int, np.ndarray],
) -> None:
    """The calibrated pin at every used touch-up, the target -> pin residual arrows and the
    rejected touch-ups with their reasons (static)."""
    rec.log(
        "world/pins",
        rr.Points3D(pins[inl], radii=0.002, colors=[BLUE] * int(inl.sum())),
        static=True,
    )
    if targets:
        tg = np.array([targets.get(int(t), np.full(3, np.nan)) for t in tu["target_id"]])
        ok = inl & np.all(np.isfinite(tg), axis=1)
        rec.log(
            f"world/residuals_x{RESIDUAL_SCALE}",
            rr.Arrows3D(
                origins=tg[ok],
                vectors=(pins[ok] - tg[ok]) * RESIDUAL_SCALE,
                colors=[ORANGE] * int(ok.sum()),
                labels=[
                    f"#{int(t)}: {np.linalg.norm(pins[i] - tg[i]) * 1e3:.3f} mm"
                    for i, t in zip(
                        np.flatnonzero(ok), tu["touchup_id"].to_numpy()[ok], strict=True
                    )
                ],
            ),
            static=True,
        )
    rej_mask = ~inl & np.all(np.isfinite(pins), axis=1)
    if rej_mask.any():
        rej = tu[rej_mask]
        rec.log(
            "world/rejected",
            rr.Points3D(
                pins[rej_mask],
                radii=0.004,
                colors=[RED] * len(rej),
                labels=[
                    f"#{t}: {why}" for t, why in zip(rej["touchup_id"], rej["reason"], strict=True)
                ],
                show_labels=True,
            ),
            static=True,
        )


def _log_camera(
    rec: rr.RecordingStream,
    cam: tuple[np.ndarray, float, tuple[int, int]],
    images: dict[int, Frame] | None,
    d0: tuple[float, float, float] | None,
    p_pin: np.ndarray | None,
) -> None:
    """The nominal camera (:func:`camera_guess`) on the flange and its pinhole (static)."""
    T_fc, f, (w, h) = cam
    for im in (images or {}).values():  # the real image size when one decodes
        try:
            h, w = im.gray.shape[:2]
            break
        except Exception:  # noqa: BLE001 - an undecodable frame is just not shown
            continue
    rec.log(
        "world/robot/calibrated/flange/camera",
        rr.Transform3D(translation=T_fc[:3, 3], mat3x3=T_fc[:3, :3]),
        static=True,
    )
    rec.log(
        "world/robot/calibrated/flange/camera/image",
        rr.Pinhole(
            focal_length=f,
            width=w,
            height=h,
            # the pin is on the optical axis and shows at the designated pixel
            principal_point=[d0[0] + PX, d0[1] + PX] if d0 is not None else None,
            camera_xyz=rr.ViewCoordinates.RDF,
            image_plane_distance=float(np.linalg.norm(p_pin)) if p_pin is not None else 0.1,
        ),
        static=True,
    )


def _skeletons(
    rec: rr.RecordingStream,
    path: str,
    indexes: list[rr.TimeColumn],
    strips: list[Any],
    radius: float,
    colors: list[Any],
    labels: list[str],
) -> None:
    """One robot skeleton per drawn touch-up row, sent as columns (``rr.send_columns``)."""
    rec.send_columns(
        path,
        indexes=indexes,
        columns=rr.LineStrips3D.columns(
            strips=strips, radii=[radius] * len(strips), colors=colors, labels=labels
        ),
    )


class _Timelines:
    """The time of each touch-up row: ``touchup`` (its id) and ``stamp`` (its last capture),
    the stamp only when every touch-up has one (a column has no gaps)."""

    def __init__(self, tu: pd.DataFrame) -> None:
        stamps = tu["stamp_ns"].to_numpy(dtype=np.int64) if "stamp_ns" in tu else None
        self.touch = tu["touchup_id"].to_numpy().astype(np.int64)
        self.stamps = stamps if stamps is not None and bool(np.all(stamps > 0)) else None

    def columns(self, rows: np.ndarray) -> list[rr.TimeColumn]:
        """The time columns of the touch-ups at positions ``rows``."""
        cols = [rr.TimeColumn("touchup", sequence=self.touch[rows])]
        if self.stamps is not None:
            cols.append(rr.TimeColumn("stamp", timestamp=self.stamps[rows].astype("M8[ns]")))
        return cols

    def set(self, rec: rr.RecordingStream, row: int) -> None:
        """Make the touch-up at position ``row`` the stream's current time."""
        rec.set_time("touchup", sequence=int(self.touch[row]))
        if self.stamps is not None:
            rec.set_time("stamp", timestamp=np.datetime64(int(self.stamps[row]), "ns"))


def _log_pose_columns(
    rec: rr.RecordingStream,
    tu: pd.DataFrame,
    inl: np.ndarray,
    when: _Timelines,
    drawn: np.ndarray,
    q: np.ndarray,
    nominal: Chain | None,
    calibrated: Chain | None,
    p_pin: np.ndarray | None,
) -> None:
    """The rejected touch-ups' log lines, the nominal and calibrated skeletons at the rows
    ``drawn`` and the calibrated flange there: one columnar chunk per entity
    (``rr.send_columns``), not one log call per touch-up."""
    sk_nom = skeleton_points(nominal, q) if nominal is not None else None
    sk_cal = skeleton_points(calibrated, q) if calibrated is not None else None
    T_flange = None
    if calibrated is not None:
        T_pin = fk(calibrated, q)
        T_flange = T_pin.copy()
        if p_pin is not None:
            T_flange[:, :3, 3] -= np.einsum("nij,j->ni", T_pin[:, :3, :3], p_pin)
    touch = when.touch
    targets_col = tu["target_id"].tolist()
    reasons = tu["reason"].tolist()
    rej_rows = np.flatnonzero(~inl)
    if rej_rows.size:
        rec.send_columns(
            "log/rejected",
            indexes=when.columns(rej_rows),
            columns=rr.TextLog.columns(
                text=[
                    f"touch-up {touch[i]} (target {targets_col[i]}) rejected: {reasons[i]}"
                    for i in rej_rows
                ],
                level=["WARN"] * rej_rows.size,
            ),
        )
    n = int(drawn.size)
    if n and sk_nom is not None:
        _skeletons(
            rec,
            "world/robot/nominal",
            when.columns(drawn),
            [sk_nom[i] for i in drawn],
            0.003,
            [GREY] * n,
            ["nominal"] * n,
        )
    if n and sk_cal is not None:
        status = ["used" if inl[i] else f"rejected: {reasons[i]}" for i in range(len(touch))]
        labels = [f"#{touch[i]} target {targets_col[i]} ({status[i]})" for i in drawn]
        colors = [BLUE if inl[i] else RED for i in drawn]
        _skeletons(
            rec,
            "world/robot/calibrated",
            when.columns(drawn),
            [sk_cal[i] for i in drawn],
            0.004,
            colors,
            labels,
        )
    if n and T_flange is not None:
        rec.send_columns(
            "world/robot/calibrated/flange",
            indexes=when.columns(drawn),
            columns=rr.Transform3D.columns(
                translation=T_flange[drawn, :3, 3], mat3x3=T_flange[drawn, :3, :3]
            ),
        )


def _log_images(
    rec: rr.RecordingStream,
    data: RunData,
    when: _Timelines,
    drawn: np.ndarray,
    frames: dict[int, list[int]],
    shown: dict[int, Frame],
    d0: tuple[float, float, float] | None,
) -> None:
    """Each drawn touch-up's last camera image (when ``shown`` has it), with the fitted
    ellipse and the designated point, at the touch-up's time."""
    img_path = "world/robot/calibrated/flange/camera/image"
    for i in drawn:
        fr = frames.get(int(when.touch[i]), [])
        if not fr or fr[-1] not in shown:
            continue
        when.set(rec, int(i))
        blob, media = shown[fr[-1]].rrd_blob
        rec.log(img_path, rr.EncodedImage(contents=blob, media_type=media))
        ell = detection_ellipse(data, fr[-1])
        if ell is not None:
            rec.log(
                f"{img_path}/ellipse",
                rr.LineStrips2D(
                    [ellipse_polyline(*ell) + PX], colors=[GREEN], labels=["fitted ellipse"]
                ),
            )
        else:
            rec.log(f"{img_path}/ellipse", rr.Clear(recursive=False))
        if d0 is not None:
            rec.log(
                f"{img_path}/designated",
                rr.Points2D(
                    [np.asarray(d0[:2]) + PX],
                    radii=2.0,
                    colors=[RED],
                    labels=["designated"],
                ),
            )


def _blueprint() -> rrb.Blueprint:
    """3-D scene left; camera image, convergence and notes right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="robot, targets, residuals"),
            rrb.Vertical(
                rrb.Spatial2DView(origin=f"{CAMERA}/image", name="camera (last capture)"),
                rrb.TimeSeriesView(origin="convergence", name="|e_T| per iteration (px)"),
                rrb.TextDocumentView(origin="notes", name="notes"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


def _images(data: RunData) -> dict[int, Frame] | None:
    return recording_frames(data, image_frames(data))


def _notes(
    rec: rr.RecordingStream,
    data: RunData,
    notes: list[str],
    cam: tuple[np.ndarray, float, tuple[int, int]] | None,
) -> None:
    lines = [
        f"# vtcal run: {data.robot_name()}",
        "",
        f"Recorded {data.date()}. Base frame = `world` (metres, z up).",
        "",
        "* grey skeleton: nominal robot; blue: calibrated (red when the touch-up was rejected)",
        "* green points: identified targets; blue: calibrated virtual pin at each used touch-up",
        f"* orange arrows `world/residuals_x{RESIDUAL_SCALE}`: target -> pin residuals drawn "
        f"{RESIDUAL_SCALE} times longer than they are",
        "* red points `world/rejected`: rejected touch-ups, labelled with the reason",
        "* `convergence/*`: |e_T| per capture (px) on the `iteration` timeline",
        "* timelines: `touchup` (id), `stamp` (the touch-up's capture time), `iteration`",
        "",
    ]
    if cam is not None:
        lines.append(
            f"The camera frustum is a NOMINAL GUESS: the intrinsics and the camera mount are "
            f"unknown to the pipeline (never needed). Shown at the flange origin looking at the "
            f"virtual pin, focal length {cam[1]:.0f} px from s0 d / D."
        )
    if notes:
        lines += ["", "Not shown:", *[f"* {n}" for n in notes]]
    rec.log(
        "notes", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True
    )
