"""Per touch-up views of a run: its frames, designated point, detected ellipse, convergence."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.report.data import RunData

FRAME_COLS = ("frame", "frame_index", "image_index", "index")


def frame_col(df: pd.DataFrame | None) -> str | None:
    """Name of the frame-index column of frames/detections (tolerant)."""
    if df is None:
        return None
    return next((c for c in FRAME_COLS if c in df.columns), None)


def designated(data: RunData) -> tuple[float, float, float] | None:
    """``(u0, v0, s0)`` px from the recording metadata, or None."""
    m = data.meta
    try:
        return (
            float(m["designated_u"]),
            float(m["designated_v"]),
            float(m.get("designated_size_px", "nan")),
        )
    except (KeyError, ValueError):
        return None


def touchup_frames(data: RunData) -> dict[int, list[int]]:
    """``{touchup_id: [frame index, ...]}`` of each touch-up's captures, in order.

    From a ``touchup_id`` column of frames.parquet, else list-valued ``frames``
    columns of the touch-up table, else a single ``frame``/``last_frame`` column,
    else by matching the touch-up's ``stamp_ns`` to a frame's stamp. Made once per
    load (``data.derived``).
    """
    if "touchup_frames" not in data.derived:
        data.derived["touchup_frames"] = _touchup_frames(data)
    return {k: list(v) for k, v in data.derived["touchup_frames"].items()}


def _touchup_frames(data: RunData) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    fr = data.frames
    fc = frame_col(fr)
    if fr is not None and fc is not None and "touchup_id" in fr.columns:
        sub = fr[
            pd.notna(fr["touchup_id"]) & (pd.to_numeric(fr["touchup_id"], errors="coerce") >= 0)
        ]
        for tid, g in sub.groupby("touchup_id"):
            out[int(str(tid))] = [int(i) for i in g.sort_values(fc)[fc]]
        if out:
            return out
    tu = data.touchup_table()
    if tu is None:
        return out
    for c in ("frames", "frame_indices", "capture_frames"):
        if c in tu.columns:
            for _, r in tu.iterrows():
                v = r[c]
                if v is not None and len(v):
                    out[int(r["touchup_id"])] = [int(i) for i in v]
            return out
    for c in ("last_frame", "frame", "frame_index", "final_frame"):
        if c in tu.columns:
            for _, r in tu.iterrows():
                if pd.notna(r[c]) and int(r[c]) >= 0:
                    out[int(r["touchup_id"])] = [int(r[c])]
            return out
    if fr is not None and fc is not None and "stamp_ns" in fr.columns and "stamp_ns" in tu.columns:
        by_stamp = dict(zip(fr["stamp_ns"].astype("int64"), fr[fc].astype("int64"), strict=False))
        for _, r in tu.iterrows():
            i = by_stamp.get(int(r["stamp_ns"]))
            if i is not None:
                out[int(r["touchup_id"])] = [int(i)]
    return out


def detection_ellipse(data: RunData, frame: int) -> tuple[float, float, float, float, float] | None:
    """``(u, v, s, s_minor, angle)`` of the (first) detection in a frame, or None."""
    if "detection_ellipses" not in data.derived:
        data.derived["detection_ellipses"] = _detection_ellipses(data)
    return data.derived["detection_ellipses"].get(int(frame))


def _detection_ellipses(data: RunData) -> dict[int, tuple[float, float, float, float, float]]:
    """:func:`detection_ellipse` of every frame with a finite detection, from one pass."""
    det = data.detections
    fc = frame_col(det)
    if det is None or fc is None or not {"u", "v", "s"} <= set(det.columns):
        return {}
    cols = {c: det[c].to_numpy(dtype=float) for c in ("u", "v", "s")}
    sm = det["s_minor"].to_numpy(dtype=float) if "s_minor" in det else cols["s"]
    ang = det["angle"].to_numpy(dtype=float) if "angle" in det else np.zeros(len(det))
    out: dict[int, tuple[float, float, float, float, float]] = {}
    seen: set[int] = set()
    for i, f in enumerate(det[fc].tolist()):
        if f is None or (isinstance(f, float) and not np.isfinite(f)) or int(f) in seen:
            continue
        seen.add(int(f))  # the frame's first row is its detection, finite or not
        if np.isfinite(cols["u"][i]):
            out[int(f)] = (
                float(cols["u"][i]),
                float(cols["v"][i]),
                float(cols["s"][i]),
                float(sm[i]),
                float(ang[i]),
            )
    return out


def convergence_traces(data: RunData) -> dict[int, np.ndarray]:
    """``{touchup_id: (k, 3)}`` e_T history ``(du, dv, ds)`` px of each touch-up.

    From the list-valued history columns of the touch-up table when it has them
    (``e_u_history``, ``e_v_history``, ``e_s_history``), else rebuilt from
    the detections of each touch-up's captures: ``du = u - u0``, ``dv = v - v0``,
    ``ds = s - s0`` against the designated values (recording.md). Computed once per
    load (``data.derived``): report.html and run.rrd both show them.
    """
    if "convergence_traces" not in data.derived:
        data.derived["convergence_traces"] = _convergence_traces(data)
    got: dict[int, np.ndarray] = data.derived["convergence_traces"]
    return got


def _convergence_traces(data: RunData) -> dict[int, np.ndarray]:
    tu = data.touchup_table()
    out: dict[int, np.ndarray] = {}
    if tu is not None:
        for names in (
            ("e_u_history", "e_v_history", "e_s_history"),
            ("e_u_px", "e_v_px", "e_s_px"),
            ("du_px", "dv_px", "ds_px"),
        ):
            if all(n in tu.columns for n in names):
                for _, r in tu.iterrows():
                    cols = [
                        np.asarray(r[n] if r[n] is not None else [], dtype=float) for n in names
                    ]
                    k = min(len(c) for c in cols)
                    if k:
                        out[int(r["touchup_id"])] = np.stack([c[:k] for c in cols], axis=1)
                return out
    d0 = designated(data)
    det = data.detections
    fc = frame_col(det)
    if d0 is None or det is None or fc is None or not {"u", "v", "s"} <= set(det.columns):
        return out
    det_i = det.set_index(fc)
    for tid, frames in touchup_frames(data).items():
        if len(frames) < 2:
            continue
        rows = det_i.reindex(frames)
        e = np.stack(
            [
                rows["u"].to_numpy(float) - d0[0],
                rows["v"].to_numpy(float) - d0[1],
                rows["s"].to_numpy(float) - d0[2],
            ],
            axis=1,
        )
        e = e[np.all(np.isfinite(e), axis=1)]
        if len(e):
            out[tid] = e
    return out


#: camera images run.rrd logs at most (each touch-up's last capture)
MAX_IMAGES = 200


def image_frames(data: RunData) -> list[int]:
    """Frame indices of the camera images logged: each touch-up's last capture (at most 200)."""
    tu = data.touchup_table()
    if tu is None:
        return []
    frames = touchup_frames(data)
    return [frames[int(t)][-1] for t in tu["touchup_id"] if frames.get(int(t))][:MAX_IMAGES]
