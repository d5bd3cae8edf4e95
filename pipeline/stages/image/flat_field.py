"""The sensor's fixed gain pattern (PRNU), estimated from the recording itself.

A camera's pixels do not all answer light alike: each has its own gain
``1 + delta(x)`` (photo-response non-uniformity, PRNU, about 1 % on common
sensors), fixed for the camera. Every touch-up converges to the same designated
pixel and size, so the target's edge crosses the same pixels at every converged
capture, and their gains bias the halfway crossings there alike in every
touch-up: repeated captures average the random noise, not the pattern
(docs/detection.md, "A flat field from the recording").

The recording itself measures the pattern: over hundreds of images the target
and plate pass over every pixel near the designated one, and each image's
fitted ellipse predicts what each pixel should see. Ingest keeps a crop of the
image around every clean detection (:class:`CropStore`); after the pass,
:func:`estimate_flat_field` fits, per crop, in linear light (the camera
response undone),

    L(x) = P(x) (1 - w(x)) + T(x) w(x),    w(x) = Phi(-d(x) / sigma)

with ``P``, ``T`` planes (plate and target, shading), ``d`` the signed radial
distance of pixel ``x`` from the detected ellipse and ``sigma`` the detection's
edge width. The residual ``e = L - m`` of the model ``m`` is freed of the
model's own shape error at the edge (its mean ``C h(d)`` over all crops, ``C``
the crop's contrast), and each pixel's gain error is the least-squares slope
of ``L = (1 + delta) m`` over the crops that cover it:

    delta_hat(x) = sum_k e'_k(x) m_k(x) / sum_k m_k(x)^2.

A PRNU is white (pixel to pixel), shading and the model's smooth misfits are
not: ``delta_hat`` minus its local mean over a ``HIGHPASS_PX`` box keeps the
pattern. Whether there is a pattern at all is decided by estimating it twice,
from two kinds of sample that share nothing but the sensor: ``a`` from the
samples where the pixel saw flat plate or target (``|d| > EDGE_PX``), ``b`` from
those where it saw the edge. A gain is the pixel's whatever it sees, so it
shows in both; what the image content leaves at the edge at a converged pose
(JPEG blocks, demosaicing), repeated as faithfully from touch-up to touch-up,
shows only in ``b``:

    z = sum_x a(x) b(x) / sqrt(sum_x (a(x) b(x))^2),   tau^2 = mean_x a(x) b(x)

(``z`` ~ N(0, 1) without a pattern), and the gain map is applied only when
``z > Z_MIN``. (Two halves of the images, even / odd, would see the content's
repeats too: on JPEG q90 and Bayer cells they gave z = 8.9 and 9.7, the roles
0.3 and 0.1; with a 1 % PRNU 33 / 20 on the two standard cells.) The two
estimates are combined per pixel by their variances, the edge one's raised by
what the edge samples carry beyond pattern and noise (the content's repeats,
``art^2 = mean((a - b)^2 - var_a - var_b)``; each role's noise ``kappa`` from its
even and odd images' difference, where pattern and repeats cancel), and shrunk
toward 1 by the result's noise (Wiener):

    delta = (a / var_a + b / (var_b + art^2)) / (1 / var_a + 1 / (var_b + art^2)),
    g(x) = 1 + delta tau^2 / (tau^2 + var_delta).

The detector then divides the linearised window by ``g``
(:func:`pipeline.stages.detect.detector.detect_target`'s ``gain``) and every kept image is
detected again (:func:`redetect`).

The first estimate's ellipses were fitted on the uncorrected images, so each had
already taken up the part of the pattern that moves an ellipse, which is the part
that biases a touch-up; its residuals under-report exactly that. So the pattern is
estimated a second time from the corrected ellipses (:data:`ROUNDS`,
:func:`correct_flat_field`): on the UR5e-like sensor-noise cell, eight seeds, the
mean shape error 0.0168 -> 0.0159 mm, against 0.0140 mm with the simulator's true
map divided out (docs/detection.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.special import ndtr

from pipeline.stages.detect.detector import DetectConfig, detect_target, nonlinear_response
from pipeline.stages.response.curve import Response

#: half-width of a kept crop beyond the long half-axis (px)
CROP_MARGIN_PX = 10
#: crops kept at most (bytes); beyond it no flat field is estimated (and it says so)
MAX_CROP_BYTES = 256 * 2**20
#: box (px) whose mean is taken off the per-pixel estimate: shading out, PRNU in
HIGHPASS_PX = 7
#: z (flat samples against edge samples) above which the pattern is taken as real
Z_MIN = 6.0
#: a pixel farther than this from the ellipse (px) saw flat plate or target
EDGE_PX = 3.0
#: estimates, each from the ellipses the one before corrected
ROUNDS = 2
#: bins of the signed edge distance (px) for the model's shape error at the edge
_BINS = np.arange(-8.0, 8.0001, 0.25)
#: crops used for that shape error (it needs no more)
_PROFILE_CROPS = 64
#: which distance bins (``np.digitize(d, _BINS)``) lie farther than EDGE_PX from the edge
_FLAT_BIN = np.concatenate([[True], (_BINS[1:] <= -EDGE_PX) | (_BINS[:-1] >= EDGE_PX), [True]])


@dataclass(frozen=True)
class Crop:
    """One clean detection's image crop.

    Attributes
    ----------
    k : the image's row in the detections (0-based message order)
    v0, u0 : the crop's top-left pixel in the image
    pixels : (h, w) the grey crop (the image's dtype)
    ellipse : ``(u, v, s, s_minor, angle)`` of the detection (px, rad)
    edge_sigma : the detection's edge width (px)
    """

    k: int
    v0: int
    u0: int
    pixels: np.ndarray
    ellipse: tuple[float, float, float, float, float]
    edge_sigma: float


def _ellipse(det: dict[str, Any]) -> tuple[float, float, float, float, float]:
    """``(u, v, s, s_minor, angle)`` of a detection (:data:`Crop.ellipse`)."""
    u, v, s, sm, ang = (float(det[k]) for k in ("u", "v", "s", "s_minor", "angle"))
    return u, v, s, sm, ang


@dataclass
class CropStore:
    """Crops of every clean detection, up to :data:`MAX_CROP_BYTES`.

    Attributes
    ----------
    crops : the crops kept, in message order
    n_bytes : their size
    overflow : True once a crop did not fit (then no flat field is estimated)
    max_bytes : the limit
    image_shape : the first kept image's ``(H, W)``
    mixed : True once an image of another size came (then no flat field either)
    """

    crops: list[Crop] = field(default_factory=list)
    n_bytes: int = 0
    overflow: bool = False
    max_bytes: int = MAX_CROP_BYTES
    image_shape: tuple[int, int] | None = None
    mixed: bool = False

    def add(self, k: int, grey: np.ndarray, det: dict[str, Any]) -> None:
        """Keep the crop of image ``k`` around its detection (clean detections only)."""
        if self.overflow or not (det.get("found") and det.get("quality_ok")):
            return
        u, v, s = float(det["u"]), float(det["v"]), float(det["s"])
        if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(s)):
            return
        H, W = grey.shape
        if self.image_shape is None:
            self.image_shape = (H, W)
        elif self.image_shape != (H, W):
            self.mixed = True
            return
        hw = int(math.ceil(0.5 * s)) + CROP_MARGIN_PX
        v0, v1 = max(int(round(v)) - hw, 0), min(int(round(v)) + hw + 1, H)
        u0, u1 = max(int(round(u)) - hw, 0), min(int(round(u)) + hw + 1, W)
        if v1 <= v0 or u1 <= u0:
            return
        pix = np.array(grey[v0:v1, u0:u1], copy=True)
        if self.n_bytes + pix.nbytes > self.max_bytes:
            self.overflow = True
            return
        sig = float(det.get("edge_sigma_px", float("nan")))
        self.crops.append(Crop(k, v0, u0, pix, _ellipse(det), sig if math.isfinite(sig) else 1.0))
        self.n_bytes += pix.nbytes


@dataclass(frozen=True)
class FlatField:
    """The gain pattern found in a recording.

    Attributes
    ----------
    gain : (H, W) float64 or None
        ``g(x)`` to divide the linearised image by (1 where nothing is known);
        None when no pattern was found (nothing to correct).
    summary : what was found, for ``recording.json`` and the report: ``applied``,
        ``z``, ``prnu_percent`` (``100 tau``), ``n_images``, ``n_pixels``, ``note``.
    """

    gain: np.ndarray | None
    summary: dict[str, Any]


def _geometry(c: Crop) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets ``du, dv`` from the centre and signed radial distance ``d`` from the ellipse.

    ``d = r - r / rho`` with ``rho`` the ellipse's normalised radius
    ``sqrt((x'/a)^2 + (y'/b)^2)`` (``x', y'`` along its axes): negative inside.
    """
    h, w = c.pixels.shape
    u, v, s, sm, ang = c.ellipse
    vv, uu = np.mgrid[c.v0 : c.v0 + h, c.u0 : c.u0 + w].astype(np.float64)
    du, dv = uu - u, vv - v
    ca, sa = math.cos(ang), math.sin(ang)
    xp, yp = du * ca + dv * sa, -du * sa + dv * ca
    rho = np.sqrt((xp / (0.5 * s)) ** 2 + (yp / (0.5 * max(sm, 1e-6))) ** 2)
    r = np.sqrt(xp * xp + yp * yp)
    d = r - r / np.maximum(rho, 1e-12)
    return du, dv, d


def _model(c: Crop, resp: Response | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One crop in linear light: its residual from the two-plane edge model, the model, the bins.

    Returns ``(e, m, i, C)``: residual ``e = L - m`` and model ``m`` (module docstring),
    ``float32``; the distance bin ``i`` of every pixel (:data:`_BINS`); the contrast
    ``C = P - T`` at the centre. The six coefficients by the normal equations.
    """
    L = resp.linearise(c.pixels) if resp is not None else c.pixels.astype(np.float64)
    du, dv, d = _geometry(c)
    w = ndtr(-d / max(c.edge_sigma, 0.3))
    A = np.stack([1.0 - w, (1.0 - w) * du, (1.0 - w) * dv, w, w * du, w * dv], axis=-1)
    A2 = A.reshape(-1, 6)
    try:
        coef = np.linalg.solve(A2.T @ A2, A2.T @ L.ravel())
    except np.linalg.LinAlgError:
        coef = np.linalg.lstsq(A2, L.ravel(), rcond=None)[0]
    m = (A @ coef).reshape(L.shape)
    i = np.digitize(d, _BINS).astype(np.uint8)
    return (L - m).astype(np.float32), m.astype(np.float32), i, float(coef[0] - coef[3])


def _edge_profile(
    models: list[tuple[np.ndarray, np.ndarray, np.ndarray, float]],
) -> np.ndarray:
    """Mean residual per distance bin, as a fraction of the contrast: the model's shape error.

    ``models``: :func:`_model` of the crops it is taken over.
    """
    sums = np.zeros(_BINS.size + 1)
    cnt = np.zeros(_BINS.size + 1)
    for e, _, i, C in models:
        if abs(C) < 1e-9:
            continue
        sums += np.bincount(i.ravel(), weights=e.ravel() / C, minlength=sums.size)
        cnt += np.bincount(i.ravel(), minlength=cnt.size)
    out: np.ndarray = sums / np.maximum(cnt, 1.0)
    out[0] = out[-1] = 0.0  # beyond the bins: plate / target, no edge
    return out


def _highpass(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``num / den`` minus its local mean over a :data:`HIGHPASS_PX` box (pixels with data)."""
    has = den > 0
    delta = np.where(has, num / np.where(has, den, 1.0), 0.0)
    k = (HIGHPASS_PX, HIGHPASS_PX)
    wsum = cv2.boxFilter(has.astype(np.float64), -1, k, normalize=False)
    dsum = cv2.boxFilter(delta, -1, k, normalize=False)
    out: np.ndarray = np.where(has, delta - dsum / np.maximum(wsum, 1.0), 0.0)
    return out


def _accumulate(
    crops: list[Crop], resp: Response | None, box: tuple[int, int, int, int]
) -> np.ndarray:
    """Sums of ``e' m`` and ``m^2`` per pixel of ``box``, by role and by parity.

    Returns ``(2, 2, 2, h, w)``: [flat, edge] x [even, odd image] x [``sum e' m``,
    ``sum m^2``], ``box = (v0, u0, v1, u1)`` the pixels any crop covers.
    """
    bv, bu, bv1, bu1 = box
    acc = np.zeros((2, 2, 2, bv1 - bv, bu1 - bu))
    step = max(len(crops) // _PROFILE_CROPS, 1)
    # the profile's crops' models are kept for the pass below (each crop modelled once)
    models = {i: _model(crops[i], resp) for i in range(0, len(crops), step)}
    prof = _edge_profile(list(models.values()))
    for i, c in enumerate(crops):
        e0, m, bins, C = models.pop(i) if i in models else _model(c, resp)
        em = (e0 - C * prof[bins]) * m
        mm = m * m
        flat = _FLAT_BIN[bins]
        h, w = c.pixels.shape
        sl = (slice(c.v0 - bv, c.v0 - bv + h), slice(c.u0 - bu, c.u0 - bu + w))
        for role, mask in ((0, flat), (1, ~flat)):
            acc[role, i % 2, 0][sl] += np.where(mask, em, 0.0)
            acc[role, i % 2, 1][sl] += np.where(mask, mm, 0.0)
    return acc


def _noise(acc_role: np.ndarray) -> float:
    """``kappa`` of one role: the residual variance, from its even and odd estimates' difference.

    ``var(delta_even - delta_odd) = kappa (1 / sum_even m^2 + 1 / sum_odd m^2)``:
    pattern and content repeats cancel, only the noise is left.
    """
    (ne, de), (no, do) = acc_role
    has = (de > 0) & (do > 0)
    if not has.any():
        return float("inf")
    diff = (_highpass(ne, de) - _highpass(no, do))[has]
    return float(np.mean(diff**2 / (1.0 / de[has] + 1.0 / do[has])))


def estimate_flat_field(
    store: CropStore, response: Response | None, shape: tuple[int, int]
) -> FlatField:
    """The recording's gain pattern from its kept crops (module docstring's maths).

    Parameters
    ----------
    store : the crops ingest kept
    response : the camera response detection used (``DetectConfig.response``)
    shape : ``(H, W)`` of the images

    Returns
    -------
    FlatField : ``gain`` None unless the flat-against-edge test finds a pattern
    """
    crops = store.crops
    base: dict[str, Any] = {"applied": False, "n_images": len(crops), "highpass_px": HIGHPASS_PX}
    if store.overflow:
        note = f"not estimated: more crops than {store.max_bytes // 2**20} MB"
        return FlatField(None, {**base, "note": note})
    if store.mixed or (store.image_shape is not None and store.image_shape != tuple(shape)):
        return FlatField(None, {**base, "note": "not estimated: images of different sizes"})
    if len(crops) < 8 or shape[0] <= 0 or shape[1] <= 0:
        return FlatField(None, {**base, "note": f"not estimated: {len(crops)} clean images"})
    resp = nonlinear_response(response)
    box = (
        min(c.v0 for c in crops),
        min(c.u0 for c in crops),
        max(c.v0 + c.pixels.shape[0] for c in crops),
        max(c.u0 + c.pixels.shape[1] for c in crops),
    )
    acc = _accumulate(crops, resp, box)
    sums = acc.sum(axis=1)  # by role: (2, 2, h, w)
    den_a, den_b = sums[0, 1], sums[1, 1]
    a = _highpass(sums[0, 0], den_a)
    b = _highpass(sums[1, 0], den_b)
    both = (den_a > 0) & (den_b > 0)
    n = int(both.sum())
    if n < 50:
        return FlatField(None, {**base, "n_pixels": n, "note": f"not estimated: {n} pixels"})
    prod = a[both] * b[both]
    z = float(prod.sum() / math.sqrt(max(float((prod**2).sum()), 1e-300)))
    tau2 = float(max(prod.mean(), 0.0))
    var_a = _noise(acc[0]) / np.where(den_a > 0, den_a, np.inf)
    var_b = _noise(acc[1]) / np.where(den_b > 0, den_b, np.inf)
    # what the edge samples carry beyond the pattern and the noise: the content's repeats
    art2 = float(max(np.mean((a - b)[both] ** 2 - var_a[both] - var_b[both]), 0.0))
    summary = {
        **base,
        "n_pixels": n,
        "z": z,
        "z_min": Z_MIN,
        "prnu_percent": 100.0 * math.sqrt(tau2),
        "edge_excess_percent": 100.0 * math.sqrt(art2),
        "flat_edge_corr": float(np.corrcoef(a[both], b[both])[0, 1]),
    }
    if not z > Z_MIN:
        note = (
            f"no fixed gain pattern (z = {z:.1f} <= {Z_MIN:g}, flat against edge samples, "
            f"{len(crops)} images, {n} pixels)"
        )
        return FlatField(None, {**summary, "note": note})
    w_a = np.where(den_a > 0, 1.0 / np.maximum(var_a, 1e-300), 0.0)
    w_b = np.where(den_b > 0, 1.0 / np.maximum(var_b + art2, 1e-300), 0.0)
    wsum = w_a + w_b
    has = wsum > 0
    delta = np.where(has, (w_a * a + w_b * b) / np.where(has, wsum, 1.0), 0.0)
    var = np.where(has, 1.0 / np.where(has, wsum, 1.0), np.inf)
    gain = np.ones(shape)
    gain[box[0] : box[2], box[1] : box[3]] = 1.0 + delta * (tau2 / (tau2 + var))
    note = (
        f"fixed gain pattern (PRNU) {100.0 * math.sqrt(tau2):.2f} % found "
        f"(z = {z:.1f}, flat against edge samples, {len(crops)} images, {n} pixels): corrected"
    )
    return FlatField(gain, {**summary, "applied": True, "note": note})


def redetect(
    store: CropStore,
    rows: list[dict[str, Any]],
    cfg: DetectConfig,
    flat: FlatField,
    shape: tuple[int, int],
) -> int:
    """Detect every kept image again with the gain pattern divided out; rows replaced in place.

    Each crop is pasted into an image of the crop's border median (the plate), so the
    detector's coarse search sees what it saw; the detection's own centre steers it.
    Returns the number of images detected again.
    """
    if flat.gain is None:
        return 0
    n = 0
    for c in store.crops:
        canvas = np.empty(shape, dtype=c.pixels.dtype)
        border = np.concatenate([c.pixels[0], c.pixels[-1], c.pixels[:, 0], c.pixels[:, -1]])
        canvas[...] = np.median(border).astype(c.pixels.dtype)
        h, w = c.pixels.shape
        canvas[c.v0 : c.v0 + h, c.u0 : c.u0 + w] = c.pixels
        u, v, s = c.ellipse[:3]
        rows[c.k] = detect_target(canvas, cfg, (u, v, s), gain=flat.gain)
        n += 1
    return n


def correct_flat_field(
    store: CropStore, rows: list[dict[str, Any]], cfg: DetectConfig, shape: tuple[int, int]
) -> FlatField:
    """Estimate the gain pattern and detect the kept images again, :data:`ROUNDS` times.

    Each round after the first estimates from the same pixels with the ellipses the
    round before found (module docstring). Stops at the first round that finds no
    pattern. ``rows`` are replaced in place; returns the last round's field, its
    summary with ``rounds`` done.
    """
    flat = estimate_flat_field(store, cfg.response, shape)
    done = 0
    while flat.gain is not None:
        redetect(store, rows, cfg, flat, shape)
        done += 1
        if done >= ROUNDS:
            break
        moved = CropStore(max_bytes=store.max_bytes)
        for c in store.crops:
            r = rows[c.k]
            if r["found"] and r["quality_ok"]:
                moved.crops.append(replace(c, ellipse=_ellipse(r)))
        nxt = estimate_flat_field(moved, cfg.response, shape)
        if nxt.gain is None:
            break
        flat = nxt
    return FlatField(flat.gain, {**flat.summary, "rounds": done})
