"""Self-diagnosis of the camera and the targets: what vtcal found, and what no residual can show.

A constant error of the measured long axis (a camera response taken for
linear, a print of the wrong diameter) moves every touch-up along the view by
the same amount: the identified pin absorbs it and the residuals stay small.
An error that depends on the view (an out-of-round print read along different
directions, a size bias growing with the plate's tilt) does leave a trace: the
touch-ups' residuals along the view then correlate with the tilt and with the
long axis' direction on the plate. This section shows, from the artefacts only:

* the response curve detection used and how it was chosen
  (``recording.json`` ``camera``, :mod:`pipeline.stages.response.curve`);
* the sensor's fixed gain pattern (PRNU), found and divided out or not
  (``camera`` ``flat_field``, :mod:`pipeline.stages.image.flat_field`);
* the illumination gradient across the target;
* touch-ups that stopped off target and were corrected rather than rejected;
* whether the camera had settled at each touch-up's repeated final captures,
  and the weights their averages used (:mod:`pipeline.stages.touchups.settle`);
* per-target print shape, where identification estimated one
  (``targets.parquet`` columns ``print_*``);
* the along-view residual of every used touch-up against the tilt ``theta``
  (``cos theta = axis_ratio``) and the long axis' direction ``beta`` in the
  target's plate, with the least-squares fit
  ``r_view = c0 + c1 (1 - cos theta) + c2 cos 2 beta + c3 sin 2 beta``
  (an out-of-round print gives the ``2 beta`` terms, a tilt-dependent size bias
  ``c1``); a term larger than 3 standard errors and 5 um is flagged.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pandas as pd

from pipeline.io.artefacts import read_meta
from pipeline.io.run_folder import RUN_FILES
from pipeline.kinematics.chain import fk
from pipeline.report.data import RunData

#: a fitted along-view trend must exceed this (m) and 3 standard errors to be flagged
TREND_MIN_M = 5e-6


def _row(effect: str, found: str, status: str) -> dict[str, str]:
    return {"effect": effect, "found": found, "status": status}


def _response_rows(cam: dict[str, Any]) -> tuple[list[dict[str, str]], list[str]]:
    rows: list[dict[str, str]] = []
    warn: list[str] = []
    if not cam:
        rows.append(_row("camera response", "not recorded by this run", "na"))
        return rows, warn
    resp = str(cam.get("response", "linear"))
    src = str(cam.get("response_source", ""))
    note = str(cam.get("note", ""))
    status = "ok"
    if src == "assumed":
        status = "warn"
        warn.append(
            "The camera's response curve could not be estimated from the edges and linear was "
            "assumed. If the camera encodes its output (sRGB, a gamma), every long axis is read "
            "short or long by the same amount (about 0.4 px at 0.8 px edge width: millimetres of "
            "pin depth), and no residual shows it: declare camera_response in the metadata."
        )
    elif "neither" in note:
        status = "warn"
        warn.append(
            "Neither a linear nor an sRGB response explains the target edges well: the pin depth "
            "may carry a constant error no residual shows. Declare the camera's curve "
            "(camera_response) if it is known."
        )
    sat = cam.get("saturated_fraction")
    if isinstance(sat, (int, float)) and math.isfinite(sat) and sat > 0.01:
        status = "warn"
        warn.append(
            f"{100 * sat:.0f} % of the pixels at the target's edge are saturated. A clipped plate "
            "(or target) level moves the halfway contour: every long axis reads short or long by "
            "the same amount (about 0.3 px at 45 % over-exposure: tenths of a millimetre of pin "
            "depth) and no residual shows it. Detection corrects it where the edge profile shows "
            "the hidden level (see 'clipped edges'); the correction assumes a Gaussian edge. "
            "Record with a lower exposure."
        )
    found = {
        "option": f"{resp} (given on the command line)",
        "metadata": f"{resp} (declared in the recording's metadata)",
    }.get(src, note or resp)
    if src == "estimated" and resp == "srgb":
        found += (
            ". A pure power law gamma 2.2 looks the same to the edges but reads the long axis "
            "about 0.03 px differently (tens of micrometres of pin depth): if the camera's "
            "curve is known, declare it (camera_response)"
        )
    rows.append(_row("camera response", found, status))
    g = cam.get("illumination_gradient")
    if g is not None and isinstance(g, (int, float)) and math.isfinite(g):
        gmax = float(cam.get("illumination_gradient_max", g))
        rows.append(
            _row(
                "illumination across the target",
                f"{100 * g:.1f} % change across one target diameter (median over "
                f"{int(cam.get('n_images', 0))} images; largest {100 * gmax:.1f} %); "
                "the detector's level surfaces follow it",
                "ok" if gmax < 0.3 else "warn",
            )
        )
    return rows, warn


def flat_field_rows(cam: dict[str, Any]) -> list[dict[str, str]]:
    """What ingest found of the sensor's fixed gain pattern (:mod:`pipeline.stages.image.flat_field`)."""
    ff = cam.get("flat_field")
    if not isinstance(ff, dict):
        return []
    note = str(ff.get("note", ""))
    if ff.get("applied"):
        found = (
            f"{note}; every kept image detected again with it divided out "
            f"({int(ff.get('rounds', 1))} rounds)"
        )
        return [_row("sensor gain pattern (PRNU)", found, "ok")]
    status = "na" if note.startswith("not estimated") else "ok"
    return [_row("sensor gain pattern (PRNU)", note, status)]


def _corrected_rows(inl: pd.DataFrame | None) -> list[dict[str, str]]:
    if inl is None or "note" not in inl:
        return []
    n = int(inl["note"].astype(str).str.contains("not converged, corrected").sum())
    if not n:
        return []
    return [
        _row(
            "touch-ups that stopped off target",
            f"{n} corrected by the residual correction and kept (their controller stopped "
            "outside the thresholds; see the touch-up notes)",
            "ok",
        )
    ]


def clip_rows(det: pd.DataFrame | None) -> list[dict[str, str]]:
    """What the clipped-edge correction did (detections' ``clip_correction_px``)."""
    if det is None or "clip_correction_px" not in det or "found" not in det:
        return []
    c = pd.to_numeric(det.loc[det["found"].astype(bool), "clip_correction_px"], errors="coerce")
    c = c[np.isfinite(c)]
    n = int((c != 0).sum())
    if not n:
        return []
    moved = c[c != 0]
    return [
        _row(
            "clipped edges",
            f"{n} of {len(c)} detections had a clipped bright level; their long axis was "
            f"corrected by {moved.mean():+.3f} px on average ({moved.min():+.3f} to "
            f"{moved.max():+.3f}) by a censored fit of the edge profile",
            "warn",
        )
    ]


#: relative error of the image Jacobian's size row assumed for the warning (2 mm probes
#: along the view, ~0.01 px long-axis noise: 0.5-1.5 % per target measured on vtcal's cells)
SIZE_ROW_REL_ERROR = 0.01
#: mean along-view correction (m) above which the pin error it implies is worth a warning
SIZE_CORRECTION_WARN_M = 5e-4


def size_correction_rows(tu: pd.DataFrame | None) -> tuple[list[dict[str, str]], list[str]]:
    """The mean residual correction of the touch-ups, and the pin error it can leave.

    A controller that measures the long axis differently from vtcal (an encoded
    image read as linear, a binary blob, another detector) stops every touch-up
    the same amount off in size. The residual correction moves each one by
    ``-J^-1 e_T``, ~0.3 mm per 0.1 px of long axis along the view, and an error
    ``x`` of the image Jacobian's size row moves the pin by ``x`` times that mean:
    a constant no residual shows (``docs/detection.md``, "Real cameras").
    """
    if tu is None or not {"dx_flange", "dy_flange", "dz_flange"} <= set(tu.columns):
        return [], []
    ok = tu["converged"].astype(bool) if "converged" in tu else pd.Series(True, index=tu.index)
    if "lost" in tu:
        ok &= ~tu["lost"].astype(bool)
    d = tu.loc[ok, ["dx_flange", "dy_flange", "dz_flange"]].to_numpy(dtype=float)
    d = d[np.all(np.isfinite(d), axis=1)]
    if not len(d):
        return [], []
    mean = float(np.linalg.norm(d.mean(axis=0)))
    es = ""
    if "e_s_px" in tu:
        es = f", remaining long axis {float(np.nanmean(tu.loc[ok, 'e_s_px'])):+.2f} px on average"
    pin = SIZE_ROW_REL_ERROR * mean
    flagged = mean > SIZE_CORRECTION_WARN_M
    rows = [
        _row(
            "residual correction (mean)",
            f"{1e3 * mean:.2f} mm{es}; at a {100 * SIZE_ROW_REL_ERROR:.0f} % error of the image "
            f"Jacobian's size row that is {1e6 * pin:.0f} um of pin no residual shows",
            "warn" if flagged else "ok",
        )
    ]
    warn = []
    if flagged:
        warn.append(
            f"The touch-ups stopped on average {1e3 * mean:.2f} mm from where vtcal's detector "
            "puts the target (the controller measures the size differently). The residual "
            "correction removes it through the image Jacobian, whose size row is known to about "
            f"{100 * SIZE_ROW_REL_ERROR:.0f} %: the pin may carry ~{1e6 * pin:.0f} um of "
            "constant error. Converge the touch-ups with the same detection, or probe further "
            "along the view."
        )
    return rows, warn


def settle_rows(data: RunData) -> list[dict[str, str]]:
    """Whether the camera had settled at the touch-ups' repeated final captures.

    From ``touchups.parquet``'s ``vtcal.settle`` metadata
    (:func:`pipeline.stages.touchups.settle.settle_summary`): the scatter of each
    capture before the last against the last, the weights the averages used, and
    the one-mode swing fit of the centre (:mod:`pipeline.stages.touchups.swing`).
    """
    path = data.run_dir / RUN_FILES["touchups"]
    try:
        found = json.loads(read_meta(path).get("settle", "{}")) if path.exists() else {}
    except (OSError, ValueError):
        return []
    rows = []
    for key, what in (("centre", "centre"), ("size", "long axis")):
        part = found.get(key) or {}
        if not part:
            continue
        if not part.get("tested"):
            rows.append(
                _row(
                    f"camera settle ({what})",
                    "fewer than three repeated captures at the end of a touch-up: not tested",
                    "na",
                )
            )
            continue
        sc = ", ".join(f"{x:.3f}" for x in part.get("scatter_px", []))
        p_value = float(part.get("p_value", math.nan))
        if part.get("weighted"):
            wt = ", ".join(f"{x:.2f}" for x in part.get("weights", []))
            sw = part.get("swing")
            text = (
                f"still swinging: the captures 1, 2, ... before the last differ from it by "
                f"{sc} px RMS (p = {p_value:.2g}); {'weights' if sw else 'averaged with weights'}"
                f" {wt} (the last first)"
            )
            if sw:
                text += (
                    f", used for the long axis' angle; the centre itself is a one-mode fit "
                    f"of the swing over {sw['n']} touch-ups (decay {sw['r']:.2f} and phase "
                    f"step {sw['delta_deg']:.0f} deg per capture, {sw['spacing_s']:.2f} s "
                    f"apart): it takes out the {sw['swing_last_px']:.3f} px RMS of swing left "
                    f"in the last capture"
                )
            elif key == "centre" and "swing" in part:
                text += "; one-mode swing fit not used (too few touch-ups or unequal spacing)"
        else:
            text = (
                f"settled: the captures before the last differ from it by {sc} px RMS, "
                f"no dependence on their place (p = {p_value:.2g}); plain means"
            )
        rows.append(_row(f"camera settle ({what})", text, "ok"))
    return rows


def frame_rows(identify: dict[str, Any] | None) -> list[dict[str, str]]:
    """The map that took the corrections into the calibrated flange frame (identify.json)."""
    ident = identify or {}
    best = ident.get("best_model")
    cf = ((ident.get("models") or {}).get(best) or ident).get("correction_frame")
    if not isinstance(cf, dict) or "matrix_minus_identity" not in cf:
        return []
    dev = float(np.abs(np.asarray(cf["matrix_minus_identity"], dtype=float)).max())
    return [
        _row(
            "corrections in the calibrated flange frame",
            f"the nominal robot's flange translations were off by up to {1e3 * dev:.1f} "
            f"per thousand; the corrections moved by {float(cf.get('rms_change_um', 0.0)):.2f} um "
            f"RMS, up to {float(cf.get('max_change_um', 0.0)):.2f} um ({cf.get('method', '?')})",
            "ok",
        )
    ]


def _print_rows(data: RunData, model: str | None) -> list[dict[str, str]]:
    t = data.targets
    if t is None:
        return []
    cols = [c for c in t.columns if c.startswith("print_")]
    if not cols:
        return []
    if model is not None and "model" in t:
        t = t[t["model"] == model]
    out = []
    for _, r in t.iterrows():
        vals = [
            f"{c[6:].replace('_', ' ')} {float(r[c]):.3g}"
            for c in cols
            if isinstance(r[c], (int, float, np.floating)) and math.isfinite(float(r[c]))
        ]
        if vals:
            out.append(
                _row(
                    f"print shape, target {r.get('target_label', r['target_id'])}",
                    "; ".join(vals),
                    "ok",
                )
            )
    return out


def plate_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``(e1, e2)`` spanning the plane perpendicular to ``normal`` (3,)."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    e1 = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def along_view_trend(data: RunData) -> dict[str, Any] | None:
    """Fit ``r_view = c0 + c1 (1 - cos theta) + c2 cos 2beta + c3 sin 2beta`` (module docstring).

    Returns the per-touch-up points (tilt deg, beta deg, r_view um) and the fitted
    terms with standard errors, or None when the artefacts lack what it needs
    (a calibrated chain, residuals, the touch-ups' ``axis_ratio`` and flange-frame
    ``view_*`` / ``long_axis_*`` directions).
    """
    need = [
        "axis_ratio",
        *(f"view_{a}_flange" for a in "xyz"),
        *(f"long_axis_{a}_flange" for a in "xyz"),
    ]
    tu, res, chain = data.touchups, data.residuals, data.calibrated_chain()
    if tu is None or res is None or chain is None or not set(need) <= set(tu.columns):
        return None
    model = (data.identify or {}).get("best_model")
    r = res[res["model"] == model] if model is not None and "model" in res else res
    r = r[r["used"].astype(bool)] if "used" in r else r
    df = r.merge(tu[["touchup_id", *need, *data.joint_names]], on="touchup_id", how="inner")
    if len(df) < 8:
        return None
    q = df[data.joint_names].to_numpy(dtype=float)
    v_f = df[[f"view_{a}_flange" for a in "xyz"]].to_numpy(dtype=float)
    a_f = df[[f"long_axis_{a}_flange" for a in "xyz"]].to_numpy(dtype=float)
    rv = df[["rx", "ry", "rz"]].to_numpy(dtype=float)
    cos_t = np.clip(df["axis_ratio"].to_numpy(dtype=float), 0.0, 1.0)
    R = np.stack([fk(chain, qi)[:3, :3] for qi in q])
    v_b = np.einsum("nij,nj->ni", R, v_f)
    a_b = np.einsum("nij,nj->ni", R, a_f)
    r_view = np.einsum("ni,ni->n", rv, v_b)
    beta = np.full(len(df), np.nan)
    labels = df["target_id"].astype(str).to_numpy()
    for lab in np.unique(labels):
        m = labels == lab
        e1, e2 = plate_basis(v_b[m].mean(axis=0))
        beta[m] = np.arctan2(a_b[m] @ e2, a_b[m] @ e1)
    ok = np.isfinite(r_view) & np.isfinite(beta) & np.isfinite(cos_t)
    if ok.sum() < 8:
        return None
    X = np.stack([np.ones(ok.sum()), 1 - cos_t[ok], np.cos(2 * beta[ok]), np.sin(2 * beta[ok])], 1)
    # one mean per target instead of c0: each target's pin depth can differ (print diameter)
    tl = labels[ok]
    D = np.stack([(tl == lab).astype(float) for lab in np.unique(tl)], 1)
    A = np.concatenate([D, X[:, 1:]], 1)
    coef, *_ = np.linalg.lstsq(A, r_view[ok], rcond=None)
    e = r_view[ok] - A @ coef
    dof = max(len(e) - A.shape[1], 1)
    s2 = float(e @ e) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    k = D.shape[1]
    tilt_c, c2, c3 = coef[k], coef[k + 1], coef[k + 2]
    amp = float(math.hypot(c2, c3))
    amp_se = float(
        math.sqrt(max((c2 * se[k + 1]) ** 2 + (c3 * se[k + 2]) ** 2, 0.0)) / max(amp, 1e-12)
    )
    return {
        "tilt_deg": np.degrees(np.arccos(cos_t[ok])),
        "beta_deg": np.degrees(beta[ok]),
        "r_view_um": 1e6 * r_view[ok],
        "tilt_term_m": float(tilt_c),
        "tilt_term_se_m": float(se[k]),
        "roll_amp_m": amp,
        "roll_amp_se_m": amp_se,
        "n": int(ok.sum()),
    }


def _trend_rows(tr: dict[str, Any] | None) -> tuple[list[dict[str, str]], list[str]]:
    if tr is None:
        return [
            _row(
                "size bias against tilt and roll",
                "not available (needs touch-ups with view and long-axis directions and a fit)",
                "na",
            )
        ], []
    warn: list[str] = []
    rows = []
    for name, val, se, what in (
        ("tilt", tr["tilt_term_m"], tr["tilt_term_se_m"], "per unit of (1 - cos tilt)"),
        ("roll", tr["roll_amp_m"], tr["roll_amp_se_m"], "amplitude of the 2-beta term"),
    ):
        flagged = abs(val) > max(3 * se, TREND_MIN_M)
        rows.append(
            _row(
                f"size bias against {name}",
                f"{1e6 * val:+.1f} +- {1e6 * se:.1f} um along the view {what} "
                f"({tr['n']} touch-ups, residuals of the shipped model)",
                "warn" if flagged else "ok",
            )
        )
        if flagged:
            warn.append(
                f"The touch-ups' residuals along the view depend on the {name} "
                f"({1e6 * val:+.1f} um, {abs(val) / max(se, 1e-12):.1f} standard errors): the "
                "long-axis measurement depends on the view (an out-of-round print, a size bias "
                "with tilt); the calibration carries part of it."
            )
    return rows, warn


def camera_section(data: RunData) -> dict[str, Any]:
    """The report's "Camera and targets" section (rows, warnings, a plot)."""
    cam = (data.recording or {}).get("camera") or {}
    model = (data.identify or {}).get("best_model")
    rows, warn = _response_rows(cam)
    rows += flat_field_rows(cam)
    rows += clip_rows(data.detections)
    rows += _corrected_rows(data.inliers)
    rows += settle_rows(data)
    more_rows, w_corr = size_correction_rows(data.touchups)
    rows += more_rows + frame_rows(data.identify)
    warn += w_corr
    rows += _print_rows(data, model)
    tr = along_view_trend(data)
    more, w2 = _trend_rows(tr)
    rows += more
    warn += w2
    svg = ""
    if tr is not None:
        from pipeline.report.plots import along_view

        svg = along_view(tr["tilt_deg"], tr["beta_deg"], tr["r_view_um"])
    return {"rows": rows, "warnings": warn, "svg": svg, "available": bool(rows)}
