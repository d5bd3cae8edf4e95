"""Sub-pixel detection of the circular target's image ellipse.

The measuring data of one image (spec/recording.md) are the centre
``(u, v)`` and the full long axis ``s`` of the ellipse fitting the target
contour, the contour being the boundary at the grey level halfway between
target and plate. :func:`detect_target` estimates them in four steps:

1. **Coarse blob** on a 4x area-downsampled copy: plate level = median, the
   target's extreme level = min (dark on light) or max; threshold halfway;
   connected components; the blob is picked by size and, when an expected
   ``(u, v, s)`` is given, by distance to it. Competing blobs are counted and
   an ambiguity ratio reported.
2. **Local levels** in a full-resolution window around the blob: surfaces
   ``g_in(u, v)``, ``g_out(u, v)`` (planes plus one shared vignetting
   curvature, :func:`pipeline.stages.detect.edges.level_surfaces`) fitted to
   the pixels well inside and well outside the blob (absorbs shading and
   vignetting), giving the halfway level ``g_mid = (g_in + g_out) / 2`` at
   every pixel.
3. **Sub-pixel edge points**: the zero crossings of ``g - g_mid`` along every
   row and column of the window, by linear interpolation between the two
   pixel centres that straddle it. A crossing on a row is used where the
   contour normal is within 60 deg of the row (``|n_u| >= 0.5``), a crossing
   on a column where ``|n_v| >= 0.5`` (normal from a first fit). Linear
   interpolation errs in opposite directions for opposite sub-pixel phases,
   and a contour sweeps all phases, so the fit is not biased by the grid.
4. **Ellipse fit** (algebraic conic fit on normalised coordinates, then
   Gauss-Newton on the geometric distances) and a **curvature correction**:
   blurring a convex contour with an isotropic kernel of variance ``sigma^2``
   moves its halfway-level line inwards by ``sigma^2 kappa / 2`` (``kappa``
   the local curvature; for a disc of radius R: ``R - sigma^2 / (2R)``, from
   the second-order expansion of the blurred indicator). ``sigma^2`` is
   measured from the image itself: across an edge of width ``sigma``,
   ``integral p (1 - p) dn = sigma / sqrt(pi)`` for the normalised profile ``p``
   (an erf), so ``sigma = sqrt(pi) * sum p (1 - p) / perimeter``. Each edge
   point is moved out by ``sigma^2 kappa / 2`` and the ellipse refitted.

Quality figures: RMS geometric fit residual (px), completeness (share of the
ellipse's parameter angle covered by edge points), border contact, number of
competing blobs, ambiguity ratio, contrast, and the measured edge width.

Step 1 lives in :mod:`pipeline.stages.detect.blob`, the sub-pixel edge stage of
steps 2-4 in :mod:`pipeline.stages.detect.edges` and the conic and ellipse
geometry in :mod:`pipeline.stages.detect.ellipse`; this module holds the
settings, the result and the detector that strings them together (its compiled
fine stage: :mod:`pipeline.stages.detect._jit`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pipeline.stages.detect.blob import Blob, blob_window, coarse_image, pick_blob
from pipeline.stages.detect.blob import auto_polarity as _auto_polarity
from pipeline.stages.detect.edges import (
    contour_completeness,
    crossings,
    edge_width,
    level_surfaces,
    noise_bias_pq,
    unbias_crossings,
)
from pipeline.stages.detect.ellipse import (
    conic_to_params,
    ellipse_foot,
    ellipse_normals,
    fit_conic,
    refine_geometric,
)
from pipeline.stages.detect.ellipse_distance import approx_distance
from pipeline.stages.response.curve import Response, parse_response

try:  # the compiled fine stage (same steps, loops compiled by numba)
    from pipeline.stages.detect import _jit
except ImportError:  # pragma: no cover - numba missing: NumPy path
    _jit = None  # type: ignore[assignment]

#: the public names of detection, importable from here (the coarse blob search lives in
#: detect_blob, the sub-pixel edge stage in detect_edges, the ellipse geometry in
#: detect_ellipse)
__all__ = [
    "POLARITIES",
    "RESULT_KEYS",
    "DetectConfig",
    "conic_to_params",
    "detect_target",
    "ellipse_foot",
    "ellipse_normals",
    "empty_result",
    "fit_conic",
    "noise_bias_pq",
    "refine_geometric",
]

POLARITIES = ("dark_on_light", "light_on_dark")


@dataclass
class DetectConfig:
    """Detection settings.

    Attributes
    ----------
    polarity : {"dark_on_light", "light_on_dark"} or None
        None: from the recording's metadata (ingest fills it) or automatic.
    downsample : int
        Factor of the coarse blob search.
    min_area_px : float
        Smallest blob (full-resolution px^2) considered a target.
    max_area_frac : float
        Largest blob as a share of the image.
    min_contrast_frac : float
        Least ``|g_out - g_in| / max(g_out, g_in)``; lower is "no target".
    max_edge_sigma_px : float
        Edges wider than this (motion blur, out-of-focus occluder) mark the
        detection as blurred.
    min_completeness : float
        Below this share of contour the detection is flagged incomplete.
    max_residual_px : float
        A contour fit whose RMS residual exceeds this is flagged ``poor_fit`` (an
        ellipse through a blob that is not one target: on the real dot photos
        residuals of 1.3-7.9 px came with centres 2-12 px off).
    curvature_correction : bool
        Apply the blur-curvature correction of step 4.
    ambiguity_ratio : float
        A competing blob at least this fraction of the chosen one's area (and
        not clearly excluded by the expected position) flags ``ambiguous``.
    compiled : bool
        Run the fine stage compiled (:mod:`pipeline.stages.detect._jit`, numba)
        when numba is installed; False: the NumPy reference path.
    response : Response or None
        The camera's response curve (:class:`pipeline.stages.response.curve.Response`):
        the window's grey levels are linearised with its inverse before the sub-pixel
        stage (the halfway level is halfway in irradiance). None (``auto``): not known;
        ingest takes the recording's ``camera_response`` or estimates it
        (:func:`pipeline.stages.image.response_estimate.estimate_response`); alone,
        linear. A spec string (a command line, JSON) is parsed once, on construction;
        :meth:`to_dict` writes the spec.
    clip_correction : bool
        Where the bright side of the edge is clipped at the image type's top code
        (an over-exposed plate), move the contour to where the unclipped halfway
        level would be, by a censored fit of the edge profile
        (:mod:`pipeline.stages.detect.saturation`); the long and short axes grow by the
        ``clip_correction_px`` of the result.
    """

    polarity: str | None = None
    downsample: int = 4
    min_area_px: float = 30.0
    max_area_frac: float = 0.25
    min_contrast_frac: float = 0.25
    max_edge_sigma_px: float = 2.0
    min_completeness: float = 0.9
    max_residual_px: float = 1.0
    curvature_correction: bool = True
    ambiguity_ratio: float = 0.5
    compiled: bool = True
    response: Response | None = None
    clip_correction: bool = True

    def __post_init__(self) -> None:
        r: Any = self.response
        if isinstance(r, str):  # a spec from a command line or JSON: parsed here, once
            self.response = parse_response(r)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["response"] = self.response.spec if self.response is not None else "auto"
        return d


#: keys of the dict :func:`detect_target` returns (also the detections columns)
RESULT_KEYS = (
    "found",
    "u",
    "v",
    "s",
    "s_minor",
    "angle",
    "s_inv",
    "residual_px",
    "completeness",
    "border_contact",
    "n_blobs",
    "ambiguity",
    "ambiguous",
    "contrast",
    "edge_sigma_px",
    "clip_correction_px",
    "n_edge_points",
    "quality_ok",
    "reason",
)


def empty_result(reason: str, n_blobs: int = 0) -> dict[str, Any]:
    nan = float("nan")
    return {
        "found": False,
        "u": nan,
        "v": nan,
        "s": nan,
        "s_minor": nan,
        "angle": nan,
        "s_inv": nan,
        "residual_px": nan,
        "completeness": 0.0,
        "border_contact": False,
        "n_blobs": n_blobs,
        "ambiguity": 0.0,
        "ambiguous": False,
        "contrast": nan,
        "edge_sigma_px": nan,
        "clip_correction_px": nan,
        "n_edge_points": 0,
        "quality_ok": False,
        "reason": reason,
    }


def nonlinear_response(r: Response | None) -> Response | None:
    """The response to undo; None when linear or not known (nothing to undo)."""
    return None if r is None or r.is_linear else r


def detect_target(
    image: np.ndarray,
    config: DetectConfig | None = None,
    expected: tuple[float, float, float] | None = None,
    gain: np.ndarray | None = None,
) -> dict[str, Any]:
    """Find the target ellipse in one grey image.

    The ellipse of :func:`_detect` and, where the bright side of the edge is clipped,
    its censored-profile correction (:func:`_unclip`).

    Parameters
    ----------
    image : (H, W) uint8 / uint16 / float
        Grey image, ``u`` = column, ``v`` = row, pixel centres at integers.
    config : DetectConfig
    expected : (u, v, s), optional
        Where the target is expected (e.g. the previous capture): picks the
        blob closest to it among competitors.
    gain : (H, W) float, optional
        The sensor's per-pixel gain (:mod:`pipeline.stages.image.flat_field`): the
        sub-pixel stage divides the linearised window by it.

    Returns
    -------
    dict with the keys :data:`RESULT_KEYS`: ``found``, centre ``u, v`` (px),
    full long axis ``s`` and short axis ``s_minor`` (px), long-axis ``angle``
    (rad from +u towards +v), ``s_inv = 1/s``, and the quality figures.
    ``reason`` is "" for a clean detection, else a short tag (``no_blob``,
    ``low_contrast``, ``fit_failed``, ``incomplete``, ``border``, ``ambiguous``,
    ``blurred``, ``poor_fit``). ``found`` is True only for a trustworthy detection
    (then ``quality_ok`` too); a flagged fit keeps its figures and its tag with
    ``found`` False.
    """
    cfg = config or DetectConfig()
    out = _detect(image, cfg, expected, gain)
    if out["found"] and cfg.clip_correction:
        out = _unclip(np.asarray(image), out, cfg)
    return out


def _detect(
    image: np.ndarray,
    cfg: DetectConfig,
    expected: tuple[float, float, float] | None,
    gain: np.ndarray | None = None,
) -> dict[str, Any]:
    """:func:`detect_target` without the clipped-edge correction.

    Step 1 (:mod:`pipeline.stages.detect.blob`: the coarse image, the blob, its
    full-resolution window and the core / plate masks), then steps 2-4 compiled
    (:func:`_finish_compiled`) or in NumPy (:func:`_finish_numpy`).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"detect_target needs a 2-D grey image, got shape {img.shape}")
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    k = max(int(cfg.downsample), 1)
    if min(img.shape) // k < 2:  # no coarse grid to search (a few-pixel image): nothing found
        return empty_result("no_blob")
    small, bg, lo, hi = coarse_image(img, k, cfg.compiled)
    pol = cfg.polarity or _auto_polarity(bg, lo, hi)
    if pol not in POLARITIES:
        raise ValueError(f"unknown polarity {pol!r}")
    dark = pol == "dark_on_light"
    ext = lo if dark else hi
    if abs(bg - ext) / max(bg, ext, 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast")
        out["contrast"] = abs(bg - ext)
        return out
    thr = 0.5 * (bg + ext)
    blob = pick_blob(
        small,
        thr,
        dark,
        k,
        img.shape,
        expected,
        min_area_px=cfg.min_area_px,
        max_area_frac=cfg.max_area_frac,
        ambiguity_ratio=cfg.ambiguity_ratio,
    )
    if blob is None:
        return empty_result("no_blob")
    win = blob_window(img, blob, thr, dark, k)
    if win is None:
        return empty_result("fit_failed", blob.n_blobs)
    img_roi, core_b, outer, u0, v0, u1, v1 = win
    resp = nonlinear_response(cfg.response)
    if resp is not None:
        # sub-pixel stage on irradiance: the halfway level is halfway in light, not in grey
        img_roi = resp.linearise(img_roi)
    if gain is not None:  # the sensor's fixed gain pattern divided out (flat_field)
        img_roi = np.asarray(img_roi, dtype=np.float64) / gain[v0:v1, u0:u1]
    if cfg.compiled and _jit is not None:
        return _finish_compiled(
            img_roi.astype(np.float64),
            core_b,
            outer,
            u0,
            v0,
            blob.contour,
            k,
            cfg,
            blob.n_blobs,
            blob.border,
            blob.ambiguity,
            blob.ambiguous,
        )
    return _finish_numpy(img_roi, core_b, outer, (u0, v0, u1, v1), k, cfg, blob)


def _finish_numpy(
    img_roi: np.ndarray,
    core_b: np.ndarray,
    outer: np.ndarray,
    bounds: tuple[int, int, int, int],
    k: int,
    cfg: DetectConfig,
    blob: Blob,
) -> dict[str, Any]:
    """Steps 2-4 in NumPy (the reference of :func:`_finish_compiled`).

    Level surfaces, halfway crossings, a first ellipse (:func:`_first_ellipse`), the
    crossings chosen by its normals (:func:`_select_crossings`), edge width and
    curvature correction, and the final fit. ``bounds`` is the window
    ``(u0, v0, u1, v1)``.
    """
    u0, v0, u1, v1 = bounds
    n_blobs = blob.n_blobs
    roi = img_roi.astype(np.float32)
    ua = np.arange(u0, u1, dtype=np.float32)
    va = np.arange(v0, v1, dtype=np.float32)
    g_in, lvl_in, g_out, lvl_out = level_surfaces(roi, core_b, outer, ua, va)
    mid = 0.5 * (g_in + g_out)
    amp = np.abs(g_out - g_in)
    contrast = float(abs(lvl_out - lvl_in))
    if contrast / max(abs(lvl_out), abs(lvl_in), 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast", n_blobs)
        out["contrast"] = contrast
        return out
    rows, cols = crossings(roi, mid, amp, 0.15)
    rows = rows + (u0, v0)
    cols = cols + (u0, v0)
    pts = np.concatenate([rows, cols])
    nr = rows.shape[0]
    p0 = _first_ellipse(pts, blob.contour, k)
    if p0 is None:
        return empty_result("fit_failed", n_blobs)
    chosen = _select_crossings(pts, nr, p0)
    if chosen is None:
        return empty_result("fit_failed", n_blobs)
    pts, is_row, t0, kap0, n0 = chosen
    completeness = contour_completeness(t0)
    sigma, noise = edge_width(roi, ua[None, :], va[:, None], g_in, g_out, outer, p0, completeness)
    if cfg.curvature_correction and np.isfinite(sigma) and sigma > 0:
        sig_c = min(sigma, cfg.max_edge_sigma_px)
        pts = unbias_crossings(pts, is_row, n0, sig_c, kap0)
        pts = pts + n0 * (0.5 * sig_c**2 * kap0)[:, None]
    k1 = fit_conic(pts)
    p1 = conic_to_params(k1) if k1 is not None else None
    if p1 is None:
        return empty_result("fit_failed", n_blobs)
    res, _, _ = ellipse_foot(pts, p1, newton=2)
    return _result(
        p1,
        float(np.sqrt(np.mean(res**2))),
        completeness,
        sigma,
        int(pts.shape[0]),
        contrast,
        cfg,
        n_blobs,
        blob.border,
        blob.ambiguity,
        blob.ambiguous,
    )


def _first_ellipse(
    pts: np.ndarray, contour: np.ndarray, k: int
) -> tuple[float, float, float, float, float] | None:
    """The initial ellipse: from the coarse contour, refitted to the crossings near it.

    Only crossings within ``0.75 k + 1`` px of the coarse contour's ellipse count
    (other edges out); without a coarse ellipse, all crossings. None: no ellipse.
    """
    p0 = None
    if len(contour) >= 6:
        k0 = fit_conic(contour)
        p0 = conic_to_params(k0) if k0 is not None else None
    if p0 is not None:
        near = np.abs(approx_distance(pts, p0)) < 0.75 * k + 1.0
        k0 = fit_conic(pts[near]) if near.sum() >= 8 else None
        p0 = conic_to_params(k0) if k0 is not None else None
    if p0 is None:
        k0 = fit_conic(pts) if pts.shape[0] >= 8 else None
        p0 = conic_to_params(k0) if k0 is not None else None
    return p0


def _select_crossings(
    pts: np.ndarray, nr: int, p0: tuple[float, float, float, float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The crossings chosen by the contour normal of the first fit, outliers dropped.

    A row crossing (the first ``nr`` of ``pts``) is kept where ``|n_u| >= 0.5``, a
    column crossing where ``|n_v| >= 0.5``; then those farther from ``p0`` than
    ``max(4 (1.25 mean|d| + 0.05), 0.5)`` px go. Returns ``(pts, is_row, t, kappa,
    normals)`` of the kept points (foot angle, curvature and outward normal on
    ``p0``), or None when fewer than 8 remain.
    """
    d0, t0, kap0 = ellipse_foot(pts, p0, newton=2)
    n0 = ellipse_normals(p0, t0)
    keep = np.concatenate([np.abs(n0[:nr, 0]) >= 0.5, np.abs(n0[nr:, 1]) >= 0.5])
    scale_d = 1.25 * float(np.mean(np.abs(d0[keep]))) + 0.05 if keep.any() else 1.0
    keep &= np.abs(d0) < max(4 * scale_d, 0.5)
    is_row = (np.arange(len(pts)) < nr)[keep]
    pts, t0, kap0, n0 = pts[keep], t0[keep], kap0[keep], n0[keep]
    if pts.shape[0] < 8:
        return None
    return pts, is_row, t0, kap0, n0


def _unclip(img: np.ndarray, out: dict[str, Any], cfg: DetectConfig) -> dict[str, Any]:
    """Correct a detection whose edge is clipped at the image type's top code.

    The window around the ellipse (its semi-axis plus ``4 sigma + 3`` px) is linearised
    like the sub-pixel stage's and handed to
    :func:`pipeline.stages.detect.saturation.fit_clipped_edge`, which takes the polarity from
    the levels (the darker side inside: dark on light). Nothing changes where no pixel
    of the window is at the top code.
    """
    from pipeline.stages.detect import saturation

    if img.ndim != 2:
        return out
    top = saturation.clip_level(img.dtype)
    if top is None:
        return out
    u, v, s = float(out["u"]), float(out["v"]), float(out["s"])
    sig = float(out["edge_sigma_px"]) if math.isfinite(float(out["edge_sigma_px"])) else 1.0
    pad = 0.5 * s + 4.0 * min(max(sig, 0.3), 5.0) + 3.0
    H, W = img.shape
    u0, v0 = max(int(u - pad), 0), max(int(v - pad), 0)
    u1, v1 = min(int(u + pad) + 2, W), min(int(v + pad) + 2, H)
    raw = img[v0:v1, u0:u1]
    if raw.size == 0 or not bool((raw >= top).any()):
        return out
    roi = raw.astype(np.float64)
    clip = top
    resp = nonlinear_response(cfg.response)
    if resp is not None:
        roi = np.asarray(resp.linearise(raw), dtype=np.float64)
        clip = float(np.asarray(resp.linearise(np.array([[top]], dtype=img.dtype)))[0, 0])
    ell = (u, v, 0.5 * s, 0.5 * float(out["s_minor"]), float(out["angle"]))
    fit = saturation.fit_clipped_edge(roi, float(u0), float(v0), ell, sig, clip, dark=None)
    if not fit.ok:
        return out
    out = dict(out)
    out["s"] = s + 2.0 * fit.delta_px
    out["s_minor"] = float(out["s_minor"]) + 2.0 * fit.delta_px
    out["s_inv"] = 1.0 / out["s"]
    out["clip_correction_px"] = 2.0 * fit.delta_px
    return out


def _finish_compiled(
    roi: np.ndarray,
    core: np.ndarray,
    outer: np.ndarray,
    u0: int,
    v0: int,
    contour: np.ndarray,
    k: int,
    cfg: DetectConfig,
    n_blobs: int,
    border: bool,
    ambiguity: float,
    ambiguous: bool,
) -> dict[str, Any]:
    """Steps 2-5 through :func:`pipeline.stages.detect._jit.fine_stage`."""
    assert _jit is not None
    r = _jit.fine_stage(
        roi,
        core,
        outer,
        float(u0),
        float(v0),
        np.ascontiguousarray(contour[:, 0]),
        np.ascontiguousarray(contour[:, 1]),
        0.75 * k + 1.0,
        bool(cfg.curvature_correction),
        float(cfg.max_edge_sigma_px),
        0.15,
    )
    lvl_in, lvl_out = float(r[10]), float(r[11])
    contrast = abs(lvl_out - lvl_in)
    if contrast / max(abs(lvl_out), abs(lvl_in), 1e-9) < cfg.min_contrast_frac:
        out = empty_result("low_contrast", n_blobs)
        out["contrast"] = contrast
        return out
    if r[0] != 0:
        return empty_result("fit_failed", n_blobs)
    return _result(
        (r[1], r[2], r[3], r[4], r[5]),
        float(r[6]),
        float(r[7]),
        float(r[8]),
        int(r[9]),
        contrast,
        cfg,
        n_blobs,
        border,
        ambiguity,
        ambiguous,
    )


def _result(
    p: tuple[float, float, float, float, float],
    res_rms: float,
    completeness: float,
    sigma: float,
    n_pts: int,
    contrast: float,
    cfg: DetectConfig,
    n_blobs: int,
    border: bool,
    ambiguity: float,
    ambiguous: bool,
) -> dict[str, Any]:
    """The result dict of :func:`detect_target` with the quality verdict."""
    u, v, a, b, th = p
    s = 2.0 * a
    reason = ""
    quality = True
    if completeness < cfg.min_completeness:
        reason, quality = "incomplete", False
    if border:
        reason, quality = (reason or "border"), False
    if sigma > cfg.max_edge_sigma_px:
        reason, quality = (reason or "blurred"), False
    if ambiguous:
        reason, quality = (reason or "ambiguous"), False
    if not res_rms <= cfg.max_residual_px:
        reason, quality = (reason or "poor_fit"), False
    return {
        # found means trustworthy: a flagged fit keeps its figures and its reason, but is
        # not found, so nothing downstream has to know a flag to stay safe (on the real
        # dot photos, flagged fits put centres up to 364 px off)
        "found": quality,
        "u": float(u),
        "v": float(v),
        "s": float(s),
        "s_minor": float(2.0 * b),
        "angle": float(th),
        "s_inv": float(1.0 / s),
        "residual_px": float(res_rms),
        "completeness": float(completeness),
        "border_contact": border,
        "n_blobs": n_blobs,
        "ambiguity": ambiguity,
        "ambiguous": ambiguous,
        "contrast": float(contrast),
        "edge_sigma_px": float(sigma),
        "clip_correction_px": 0.0,
        "n_edge_points": int(n_pts),
        "quality_ok": quality,
        "reason": reason,
    }
