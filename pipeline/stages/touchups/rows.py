"""Step 5 of the touch-up stage: each touch-up's averaged final captures, then its row.

:func:`final_shapes` averages every touch-up's repeated final captures (weighted
where the camera had not settled, :mod:`pipeline.stages.touchups.settle`, and the
centre then freed of the swing left in the last one, :mod:`pipeline.stages.touchups.swing`);
:func:`measurement` turns one average into the table's measurement and its
residual correction ``d_F = -J^-1 e_T`` (:mod:`pipeline.measurement.image`); :func:`touchup_row` makes the row.
The stage itself: :mod:`pipeline.stages.touchups.stage`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.measurement.image import image_error, residual_correction, touchup_error
from pipeline.stages.touchups.settle import settle, wmean
from pipeline.stages.touchups.swing import remove_swing
from pipeline.stages.touchups.types import Captures, Designated, Tilt, pose_key


def final_shapes(
    finals: list[np.ndarray], c: Captures
) -> tuple[list[list[int]], np.ndarray, dict[str, Any]]:
    """Step 5: each touch-up's final captures (good, else any found), averaged (weighted
    where the camera had not settled: touchup_settle; the centre then freed of the swing
    left in the last capture, touchup_swing), as ``(n, 5)`` u, v, s, s_minor, angle; and
    what the settle test found (:func:`pipeline.stages.touchups.settle.settle_summary`, with
    ``centre.swing`` the one-mode fit's :meth:`~pipeline.stages.touchups.swing.Swing.summary`
    when the centres were weighted, None when it was not used)."""
    u, v, s = c.u, c.v, c.s
    s_minor = c.df["s_minor"].to_numpy(float)
    ang2 = 2.0 * c.df["angle"].to_numpy(float)
    uses = []
    shape = np.full((len(finals), 5), np.nan)  # u, v, s, s_minor, long-axis angle
    for b in finals:
        uses.append([int(i) for i in b if c.good[i]] or [int(i) for i in b if c.found[i]])
    w, ws, found = settle(uses, (u, v), (s,))  # an unsettled camera's early captures
    swing = None
    if w is not None:  # still swinging: the swing left in the last capture, by one mode
        swing = remove_swing(uses, c.df["stamp_ns"].to_numpy(np.int64) * 1e-9, u, v)
        found["centre"]["swing"] = swing.summary() if swing is not None else None
    for k, use_k in enumerate(uses):
        if use_k:
            still = swing.centres.get(k) if swing is not None else None
            shape[k] = [
                still[0] if still else wmean(u, use_k, w),
                still[1] if still else wmean(v, use_k, w),
                wmean(s, use_k, ws),
                wmean(s_minor, use_k, ws),
                0.5 * np.arctan2(wmean(np.sin(ang2), use_k, w), wmean(np.cos(ang2), use_k, w)),
            ]
    return uses, shape, found


def measurement(
    use: list[int],
    m: np.ndarray,
    c: Captures,
    des: Designated,
    J: np.ndarray,
    bias: np.ndarray,
    depth_scaled: bool = True,
) -> dict[str, Any]:
    """Step 5: one touch-up's averaged measurement, its convergence and its correction.

    ``use`` are the averaged final captures (none: lost), ``m`` their averaged
    ``(u, v, s)`` (:func:`final_shapes`). The tilt ``bias``
    ``(du, dv, ds)`` turns the ellipse into the image of the circle's centre and
    the size an untilted target would show; then ``d_F = -J^{-1} e_T``.

    ``J``'s centre rows hold at the designated size ``s0`` (:func:`_jacobian_pairs`).
    A touch-up that stopped at size ``s`` sees a lateral offset ``x`` as
    ``(f / z) x = (s / D) x`` pixels, so (``depth_scaled``) its centre errors are
    taken at ``s0`` first, ``e_u s0 / s``, ``e_v s0 / s``: the lateral offset they
    stand for, whatever the depth the controller stopped at.
    """
    u0, v0, s0 = des.u0, des.v0, des.s0
    row: dict[str, Any] = {}
    if not use:
        mu = mv = ms = float("nan")
        row.update(converged=False, dx_flange=0.0, dy_flange=0.0, dz_flange=0.0)
    else:
        mu, mv, ms = float(m[0]), float(m[1]), float(m[2])
        conv = abs(mu - u0) <= des.thr and abs(mv - v0) <= des.thr and abs(ms - s0) <= des.thr_s
        # the image of the circle's centre, and the size an untilted target would show
        mu_c, mv_c, ms_c = mu + bias[0], mv + bias[1], ms - bias[2]
        d = residual_correction(J, touchup_error(mu_c, mv_c, ms_c, u0, v0, s0, depth_scaled))
        row.update(
            converged=bool(conv),
            dx_flange=float(d[0]),
            dy_flange=float(d[1]),
            dz_flange=float(d[2]),
        )
    e_u, e_v, e_sinv = image_error(mu, mv, ms, u0, v0, s0)
    row.update(
        u=mu,
        v=mv,
        s=ms,
        e_u=float(e_u),
        e_v=float(e_v),
        e_s_px=ms - s0,
        e_sinv=float(e_sinv) if np.isfinite(ms) else float("nan"),
        fit_residual_px=float(np.max(c.column("residual_px", float)[use])) if use else float("nan"),
        border_contact=bool(np.any(c.column("border_contact", bool, False)[use])) if use else False,
        ambiguous=bool(np.any(c.column("ambiguous", bool, False)[use])) if use else False,
        weight=1.0,
    )
    return row


def touchup_row(
    k: int,
    fr: np.ndarray,
    block: np.ndarray,
    m: np.ndarray,
    loop_start: int,
    label: int,
    c: Captures,
    des: Designated,
    J: tuple[np.ndarray, str],
    tilt: Tilt,
    depth_scaled: bool = True,
) -> dict[str, Any]:
    """One row of the table: touch-up ``k``, frames ``fr``, final captures ``block`` and
    their averaged ``m = (u, v, s)``.

    ``J`` is the image Jacobian of its target and where it comes from
    (``"global"`` or ``"target"``).
    """
    avg = [i for i in block if c.good[i]]
    use = avg or [i for i in block if c.found[i]]
    loop_fr = [i for i in fr if i >= loop_start]
    hist = [i for i in loop_fr if c.found[i]]
    row: dict[str, Any] = {
        "touchup_id": k,
        "target_id": label,
        "lost": len(use) == 0,
        "first_frame": int(fr[0]),
        "last_frame": int(fr[-1]),
        "loop_start_frame": int(loop_start),
        "n_probe_frames": int(sum(1 for i in fr if i < loop_start)),
        "frame_indices": [int(i) for i in fr],
        "converged_frame_indices": [int(i) for i in use],
        "n_captures": len(fr),
        "n_converged_captures": len(avg),
        "n_iterations": int(max(len({pose_key(c.T[i]) for i in loop_fr if c.still[i]}) - 1, 0)),
        "moving": bool(len(block) == 0),
        "e_u_history": [float(c.u[i] - des.u0) for i in hist],
        "e_v_history": [float(c.v[i] - des.v0) for i in hist],
        "e_s_history": [float(c.s[i] - des.s0) for i in hist],
    }
    ref = use if use else (list(block) if len(block) else [int(fr[-1])])
    q = c.Q[ref].mean(axis=0)
    for j, nm in enumerate(c.names):
        row[nm] = float(q[j])
    row["stamp_ns"] = int(c.column("stamp_ns", np.int64)[ref[-1]])
    row["jacobian_source"] = J[1]
    row.update(measurement(use, m, c, des, J[0], tilt.bias[k], depth_scaled))
    row.update(
        tilt_deg=float(tilt.tilt_deg[k]),
        tilt_resolved=bool(tilt.resolved[k]),
        bias_u_px=float(tilt.bias[k, 0]),
        bias_v_px=float(tilt.bias[k, 1]),
        bias_s_px=float(tilt.bias[k, 2]),
        view_gx=float(tilt.view_g[0]),
        view_gy=float(tilt.view_g[1]),
        view_gz=float(tilt.view_g[2]),
        axis_lx=float(tilt.axis_l[k, 0]),
        axis_ly=float(tilt.axis_l[k, 1]),
        axis_lz=float(tilt.axis_l[k, 2]),
    )
    return row
