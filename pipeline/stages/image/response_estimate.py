"""The camera's response curve estimated from the images (:mod:`pipeline.stages.response.curve`).

Estimation (per recording, from the edge profiles of the first images that
show a target). An edge blurred by a symmetric point spread function has, in
irradiance, a profile symmetric about the geometric edge; a response curve
bends it asymmetrically. Per image, with ``d`` the signed distance of a pixel
to the contour found on raw grey, and a trial inverse response ``E = g^-1(I)``::

    E(u, v) ~ (1 - F) (a0 + a1 du + a2 dv) + F (b0 + b1 du + b2 dv),
    F = Phi((d - delta) / sigma)                                        (R1)

(target and plate levels as planes, an erf edge of width ``sigma`` at offset
``delta``), fitted by variable projection: linear least squares for the six
levels inside a Levenberg-Marquardt on ``(delta, sigma)``. Residuals are
weighted by ``dI/dE`` so that they are in grey levels of the recorded image
(where the noise is). The residual sum over images ``RSS(g)`` is compared for
``linear`` and ``srgb`` (the curves cameras actually use: machine-vision
cameras often run linear, most others encode sRGB); the smaller wins. The best
power law ``gamma:G`` (bounded scalar search) is fitted too and reported; when
it fits far better than both named curves the estimate says so and asks for the
curve to be declared, but it is never used on its own evidence (next
paragraph).

What the edges cannot tell (named, not hidden): the response and the shape of
the point spread function trade against each other. To first order a response
error adds ``c F (1 - F)`` to an edge profile ``F``, and a shift of the edge
adds ``delta F'``; for a logistic profile the two are proportional, so no edge
of that shape can tell them apart, and for any profile they differ only in
shape. A fitted power law therefore carries the model error of (R1): on the
conformance sample (linear images, a discrete blur applied after pixel
integration: tails heavier than an erf) the best power law is ``gamma 0.73``
and on vtcal's own sRGB renders 2.29-2.42, whereas linear against sRGB is
decided by hundreds of noise variances in every case measured. Telling sRGB
from a pure ``gamma 2.2`` is not possible this way (they differ by ~2 noise
variances on 8 images, but by ~0.03 px of long axis, ~0.1 mm of pin depth):
a camera whose curve is neither linear nor sRGB should declare it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.special import ndtr

from pipeline.kinematics.se3 import F64
from pipeline.stages.detect.detector import DetectConfig, detect_target, ellipse_foot
from pipeline.stages.response.curve import Response
from pipeline.stages.response.edge_fit import EdgeFit, edge_spread, fit_edge


@dataclass
class ResponseEstimate:
    """What :func:`estimate_response` found.

    Attributes
    ----------
    response : the curve chosen
    gamma_fit : exponent of the best-fitting power law (NaN without data)
    delta_linear, delta_srgb : ``(RSS(curve) - RSS(best)) / sigma2`` of the two named curves
    sigma_grey : residual RMS of the best fit, grey levels of the recording
    n_images, n_pixels : edge profiles used
    illumination_gradient : median over the images of the plate's irradiance change across
        one target diameter (relative; :func:`illumination_gradient`)
    illumination_gradient_max : the largest of them
    saturated_fraction : share of the pixels within a few edge widths of the contour (in the
        images used) at the top or bottom code: a clipped level moves the halfway contour
        (:func:`saturated_fraction`)
    votes_srgb : of the ``n_images`` edge profiles, how many sRGB fits better than linear
    edge_model_misfit : the edge model (R1) does not explain the edges down to their noise
        (the curve was then chosen by the images' votes, or assumed)
    note : one line for the report and the run's summary
    """

    response: Response
    gamma_fit: float = float("nan")
    delta_linear: float = float("nan")
    delta_srgb: float = float("nan")
    sigma_grey: float = float("nan")
    n_images: int = 0
    n_pixels: int = 0
    illumination_gradient: float = float("nan")
    illumination_gradient_max: float = float("nan")
    saturated_fraction: float = 0.0
    votes_srgb: int = 0
    edge_model_misfit: bool = False
    note: str = ""

    @property
    def assumed(self) -> bool:
        """The curve was not read from the edges (none to read, too sharp, or no curve the
        images agree on): linear assumed, a guess the run's accuracy hinges on."""
        return self.n_images == 0 or self.note.startswith("linear (assumed")

    def to_dict(self) -> dict[str, Any]:
        return {
            "response": self.response.spec,
            "gamma_fit": self.gamma_fit,
            "delta_linear": self.delta_linear,
            "delta_srgb": self.delta_srgb,
            "sigma_grey": self.sigma_grey,
            "n_images": self.n_images,
            "n_pixels": self.n_pixels,
            "illumination_gradient": self.illumination_gradient,
            "illumination_gradient_max": self.illumination_gradient_max,
            "saturated_fraction": self.saturated_fraction,
            "votes_srgb": self.votes_srgb,
            "edge_model_misfit": self.edge_model_misfit,
            "note": self.note,
        }


@dataclass
class _Profile:
    """Pixels near one detected contour: distance, position, normalised grey."""

    d: F64
    du: F64
    dv: F64
    grey: F64
    x0: tuple[float, float] = (0.0, 0.8)
    diameter_px: float = 0.0
    #: fits of model (R1)-(R2) already made, by curve: ``(rss, (delta, sigma))``
    fits: dict[tuple[Any, ...], tuple[float, tuple[float, float]]] = field(default_factory=dict)


def edge_profile(
    image: np.ndarray, det: dict[str, Any], full_scale: float = 255.0
) -> _Profile | None:
    """The pixels within a few edge widths of a detected contour (for :func:`estimate_response`).

    Saturated pixels (0 or full scale) carry no response information and are left out.
    """
    if not det.get("found") or not det.get("quality_ok"):
        return None
    u, v, a, b, th = (
        float(det["u"]),
        float(det["v"]),
        0.5 * float(det["s"]),
        0.5 * float(det["s_minor"]),
        float(det["angle"]),
    )
    sig = float(det.get("edge_sigma_px", 0.8))
    if not all(math.isfinite(x) for x in (u, v, a, b, th)) or b < 4.0:
        return None
    W = float(np.clip(3.0 * (sig if math.isfinite(sig) else 0.8) + 3.0, 5.0, 10.0))
    W = min(W, 0.8 * b)
    H, Wd = image.shape
    u0, u1 = int(max(u - a - W - 1, 0)), int(min(u + a + W + 2, Wd))
    v0, v1 = int(max(v - a - W - 1, 0)), int(min(v + a + W + 2, H))
    if u1 - u0 < 8 or v1 - v0 < 8:
        return None
    vv, uu = np.mgrid[v0:v1, u0:u1]
    pts = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
    d, _, _ = ellipse_foot(pts, (u, v, a, b, th), newton=3)
    g = image[v0:v1, u0:u1].ravel().astype(float) / full_scale
    m = (np.abs(d) < W) & (g > 0.5 / full_scale) & (g < 1.0 - 0.5 / full_scale)
    if m.sum() < 50:
        return None
    du, dv = pts[m, 0] - u, pts[m, 1] - v
    dm, gm = d[m], g[m]
    x0 = (0.0, max(sig, 0.3))
    if ROUND_HARMONICS:
        c, s_ = math.cos(th), math.sin(th)
        psi = np.arctan2((-s_ * du + c * dv) / b, (c * du + s_ * dv) / a)
        dm = dm - edge_harmonics(dm, du, dv, gm, psi, x0)
    return _Profile(dm, du, dv, gm, x0, 2.0 * a)


#: the edge's own harmonics around the contour taken out before the response fit
ROUND_HARMONICS = 5


def edge_harmonics(d: F64, du: F64, dv: F64, grey: F64, psi: F64, x0: tuple[float, float]) -> F64:
    """How far the edge lies off the fitted ellipse at each pixel's angle, (N,) px.

    A print out of round (harmonics ``k = 2..5`` of its radius, 10-20 um on a
    10 mm disc: ~0.1-0.2 px here) or the contour's own fit error puts the edge
    at ``delta(psi) = sum_k a_k cos k psi + b_k sin k psi`` off the ellipse the
    distances ``d`` are measured from. Pooled over the contour, those shifts
    smear the profile by several grey levels on a sharp edge, more than the
    noise and the response's own signature. They are geometry, the same in
    every curve: fitted once on raw grey with model (R1) (``psi`` the ellipse's
    parametric angle, ``k = 1..ROUND_HARMONICS``; analytic Jacobian,
    :class:`pipeline.stages.response.edge_fit.EdgeFit`) and taken out of ``d``.
    """
    K = ROUND_HARMONICS
    ks = np.arange(1, K + 1)
    C = np.concatenate([np.cos(np.outer(psi, ks)), np.sin(np.outer(psi, ks))], axis=1)
    fit = EdgeFit(d, du, dv, grey, np.ones_like(grey), harmonics=C)
    x0_ = np.array([*x0, *np.zeros(2 * K)])
    sol = least_squares(fit.residual, x0_, jac=fit.jacobian, method="lm", xtol=1e-8)
    shift: F64 = np.clip(C @ sol.x[2:], -1.0, 1.0)
    return shift


#: the edge profile's odd shape terms (R2): a point spread function that is not Gaussian
#: (:func:`pipeline.stages.response.edge_fit.edge_spread`)
SHAPE_TERMS = True

__all__ = ["ResponseEstimate", "edge_profile", "edge_spread", "estimate_response"]


def _fit_profile(pr: _Profile, resp: Response) -> tuple[float, tuple[float, float]]:
    """Residual sum (grey^2, normalised scale) of model (R1)-(R2) under the curve ``resp``.

    Fitted by :func:`pipeline.stages.response.edge_fit.fit_edge` (variable projection, analytic
    Jacobian); a profile keeps its fit per curve, so the figures computed at the best power
    law after the search (noise, edge width, illumination) do not fit it again.
    """
    key = ("linear", 1.0, ()) if resp.is_linear else (resp.kind, resp.gamma, resp.table)
    got = pr.fits.get(key)
    if got is not None:
        return got
    E = resp.to_linear(pr.grey)
    w = 1.0 / np.maximum(resp.slope(pr.grey), 1e-6)
    x0 = np.array([*pr.x0, *((0.0, 0.0) if SHAPE_TERMS else ())], dtype=float)
    rss, x = fit_edge(pr.d, pr.du, pr.dv, E, w, x0)
    out = (rss, (float(x[0]), float(abs(x[1]))))
    pr.fits[key] = out
    return out


def _flat_noise2(pr: _Profile, resp: Response) -> tuple[float, int]:
    """Residual sum and count of the pixels more than 3 edge widths off the edge (noise alone)."""
    _, (delta, sigma) = _fit_profile(pr, resp)
    far = np.abs(pr.d - delta) > 3.0 * sigma + 1.0
    if far.sum() < 20:
        return 0.0, 0
    sub = _Profile(pr.d[far], pr.du[far], pr.dv[far], pr.grey[far], (delta, sigma))
    E = resp.to_linear(sub.grey)
    w = 1.0 / np.maximum(resp.slope(sub.grey), 1e-6)
    F = ndtr((sub.d - delta) / max(sigma, 0.05))
    A = np.stack([1 - F, (1 - F) * sub.du, (1 - F) * sub.dv, F, F * sub.du, F * sub.dv], 1)
    A = A * w[:, None]
    coef, *_ = np.linalg.lstsq(A, E * w, rcond=None)
    r = A @ coef - E * w
    return float(np.sum(r**2)), int(far.sum()) - 6


def illumination_gradient(pr: _Profile, resp: Response, diameter_px: float) -> float:
    """Relative change of the plate's irradiance across one target diameter (model R1's levels).

    ``|grad b| D / b0`` of the plate plane ``b0 + b1 du + b2 dv`` fitted in linearised
    grey: 0.15 means the light falls off by 15 % from one side of the target to the other.
    """
    _, (delta, sigma) = _fit_profile(pr, resp)
    E = resp.to_linear(pr.grey)
    F = ndtr((pr.d - delta) / max(sigma, 0.05))
    A = np.stack([1 - F, (1 - F) * pr.du, (1 - F) * pr.dv, F, F * pr.du, F * pr.dv], 1)
    coef, *_ = np.linalg.lstsq(A, E, rcond=None)
    plate = coef[3:] if coef[3] > coef[0] else coef[:3]  # the plate is the brighter side
    return float(np.hypot(plate[1], plate[2]) * diameter_px / max(abs(plate[0]), 1e-9))


def _total(profiles: Sequence[_Profile], resp: Response) -> float:
    return float(sum(_fit_profile(p, resp)[0] for p in profiles))


#: the best power law fitting the edges better than the chosen named curve by more than this
#: many noise variances per image: "neither linear nor sRGB" (with the odd profile terms
#: (R2), sRGB renders sit at 0.5 and gamma-2.2 ones at 1.2 per image, a vendor curve at 9
#: and a clipped edge at 300: bench_optics cells, seed 11, 9 touch-ups)
WARN_PER_IMAGE = 4.0

#: when the edge model does not fit the edges, a named curve is still chosen when at least
#: this share of the images prefer it (else linear is assumed and the run says so)
VOTE_SHARE = 0.8
#: ... and it fits better by at least this many (misfit-inflated) noise variances per image
VOTE_MARGIN_PER_IMAGE = 10.0


def _voted(chosen: Response, figures: dict[str, Any], why: str) -> ResponseEstimate | None:
    """The curve chosen by the images' votes when the edge model misfits (else None).

    The edge model is imperfect (a point spread function, a print or a compression
    it does not hold), but image after image prefers one curve by a margin the
    misfit does not explain: that curve, said to rest on the votes. ``figures`` are
    :class:`ResponseEstimate`'s fields but the curve and note; ``why`` the misfit.
    """
    n_img, srgb = int(figures["n_images"]), int(figures["votes_srgb"])
    agree = srgb if chosen.kind == "srgb" else n_img - srgb
    margin = abs(float(figures["delta_linear"]) - float(figures["delta_srgb"]))
    if agree < VOTE_SHARE * n_img or margin < VOTE_MARGIN_PER_IMAGE * n_img:
        return None
    return ResponseEstimate(
        chosen,
        **figures,
        edge_model_misfit=True,
        note=(
            f"{chosen.spec} (estimated by the edge profiles' votes: {agree} of {n_img} "
            f"images prefer it, by {margin:.0f} noise variances in all; {why}, so the "
            "margin is counted in the misfit's variance; if the camera's curve is known, "
            "declare it)"
        ),
    )


def estimate_from_profiles(
    profiles: Sequence[_Profile], warn_sigma2_per_image: float = WARN_PER_IMAGE
) -> ResponseEstimate:
    """Choose the response curve from edge profiles (module docstring, model R1)."""
    profiles = [p for p in profiles if p is not None]
    if not profiles:
        return ResponseEstimate(
            Response("linear"), note="no target edge to estimate from: linear assumed"
        )
    grid = np.array([0.6, 0.8, 1.0, 1.3, 1.6, 1.9, 2.2, 2.5, 2.8, 3.2])
    tot = np.array([_total(profiles, Response("gamma", float(g))) for g in grid])
    i = int(np.argmin(tot))
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    sol = minimize_scalar(
        lambda g: _total(profiles, Response("gamma", float(g))),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 2e-3},
    )
    g_best = float(sol.x)
    rss_best = min(float(sol.fun), float(tot[i]))
    n_pix = int(sum(len(p.d) for p in profiles))
    dof = max(n_pix - 8 * len(profiles) - 1, 1)
    sigma2 = rss_best / dof
    per_lin = np.array([_fit_profile(p, Response("linear"))[0] for p in profiles])
    per_srgb = np.array([_fit_profile(p, Response("srgb"))[0] for p in profiles])
    rss_lin, rss_srgb = float(per_lin.sum()), float(per_srgb.sum())
    votes_srgb = int(np.sum(per_srgb < per_lin))
    d_lin = (rss_lin - rss_best) / sigma2
    d_srgb = (rss_srgb - rss_best) / sigma2
    chosen = Response("linear") if rss_lin <= rss_srgb else Response("srgb")
    d_chosen = min(d_lin, d_srgb)
    flat = [_flat_noise2(p, Response("gamma", g_best)) for p in profiles]
    n_flat = sum(n for _, n in flat)
    sigma_flat = math.sqrt(sum(r for r, _ in flat) / n_flat) if n_flat > 0 else float("nan")
    sigma_fit = math.sqrt(sigma2)
    sigma_edge = float(
        np.median([_fit_profile(p, Response("gamma", g_best))[1][1] for p in profiles])
    )
    # the edge model (R1) must explain the edges down to the noise, and the edges must be
    # blurred enough to show a profile at all; else the estimate is model error
    unreliable = ""
    misfit = False
    if sigma_edge < 0.4:
        unreliable = f"the edges are too sharp ({sigma_edge:.2f} px) to show the response"
    elif not (sigma_fit <= 1.5 * sigma_flat + 0.5 / 255.0):
        misfit = True
        unreliable = (
            f"the edge model does not fit these edges (residual {255 * sigma_fit:.2f} grey "
            f"against {255 * sigma_flat:.2f} grey of noise)"
        )
    grads = [illumination_gradient(p, Response("gamma", g_best), p.diameter_px) for p in profiles]
    illum = (float(np.median(grads)), float(np.max(grads)))
    n_img = len(profiles)
    figures: dict[str, Any] = {
        "gamma_fit": g_best,
        "delta_linear": float(d_lin),
        "delta_srgb": float(d_srgb),
        "sigma_grey": 255.0 * sigma_fit,
        "n_images": n_img,
        "n_pixels": n_pix,
        "illumination_gradient": illum[0],
        "illumination_gradient_max": illum[1],
        "votes_srgb": votes_srgb,
    }
    voted = _voted(chosen, figures, unreliable) if misfit else None
    if voted is not None:
        return voted
    if unreliable:
        return ResponseEstimate(
            Response("linear"),
            **figures,
            edge_model_misfit=misfit,
            note=(
                f"linear (assumed: {unreliable}"
                + (
                    f"; {votes_srgb} of {n_img} images prefer sRGB, too few to tell"
                    if misfit
                    else ""
                )
                + "; if the camera encodes its output, declare it "
                "with --set camera_response=srgb or gamma:G)"
            ),
        )
    note = (
        f"{chosen.spec} (estimated from the edge profiles of {len(profiles)} images: "
        f"{'linear' if chosen.kind == 'srgb' else 'sRGB'} fits "
        f"{abs(d_lin - d_srgb):.0f} noise variances worse; best power law gamma {g_best:.2f})"
    )
    if d_chosen > warn_sigma2_per_image * len(profiles):
        note += (
            f"; neither linear nor sRGB fits the edges well (the best power law fits "
            f"{d_chosen:.0f} noise variances better): if the camera's curve is known, "
            "declare it (--set camera_response=gamma:G)"
        )
    return ResponseEstimate(chosen, **figures, note=note)


def estimate_response(
    images: Iterable[np.ndarray],
    config: Any = None,
    max_images: int = 12,
    warn_sigma2_per_image: float = WARN_PER_IMAGE,
    detections: list[dict[str, Any]] | None = None,
) -> ResponseEstimate:
    """Estimate a camera's response curve from grey images that show a target.

    Parameters
    ----------
    images : iterable of (H, W) uint8 / uint16 grey images
    config : DetectConfig, optional (its ``response`` is ignored: detection runs on raw grey)
    max_images : the first this many images with a clean detection are used
    warn_sigma2_per_image : the estimate's note warns when the chosen curve fits worse
        than the best power law by more than this many noise variances per image
    detections : optional, the raw-grey detections of the first images from an earlier
        call on the same images (the caller's list, extended with the new ones): a retry
        with more images held back detects only those (``ingest_stream.resolve_response``)

    Returns
    -------
    ResponseEstimate
    """
    cfg = dataclasses.replace(config or DetectConfig(), response=Response("linear"))
    profiles: list[_Profile] = []
    sat: list[tuple[int, int]] = []
    for i, img in enumerate(images):
        arr = np.asarray(img)
        if detections is not None and i < len(detections):
            det = detections[i]
        else:
            det = detect_target(arr, cfg)
            if detections is not None:
                detections.append(det)
        full = 65535.0 if arr.dtype == np.uint16 else 255.0
        pr = edge_profile(arr, det, full)
        if pr is not None:
            profiles.append(pr)
            sat.append(saturated_fraction(arr, det, full))
        if len(profiles) >= max_images:
            break
    est = estimate_from_profiles(profiles, warn_sigma2_per_image)
    n_sat, n_all = sum(a for a, _ in sat), sum(b for _, b in sat)
    est.saturated_fraction = n_sat / n_all if n_all else 0.0
    if est.saturated_fraction > SATURATION_WARN:
        est.note += (
            f"; {100 * est.saturated_fraction:.0f} % of the pixels at the target's edge are "
            "saturated: the halfway level between target and plate is then wrong and every long "
            "axis would read short or long by the same amount (a few tenths of a pixel, a "
            "constant pin-depth error no residual shows); detection corrects it by a censored "
            "fit of the edge profile (detections' clip_correction_px), which assumes a Gaussian "
            "edge and is less exact the more of the edge is clipped: lower the exposure"
        )
    return est


#: share of saturated pixels at the edge above which the estimate warns
SATURATION_WARN = 0.01


def saturated_fraction(image: np.ndarray, det: dict[str, Any], full: float) -> tuple[int, int]:
    """(saturated, all) pixels within 3 px of the detected contour's bounding box ring.

    Saturated: at 0 or at the top code ``full``. Counts pixels of the box
    ``|u - u_c| <= a + 3``, ``|v - v_c| <= a + 3`` whose distance to the centre is
    between ``b - 3`` and ``a + 3`` (``a``, ``b`` the semi-axes): the edge band.
    """
    if not det.get("found"):
        return 0, 0
    u, v = float(det["u"]), float(det["v"])
    a, b = 0.5 * float(det["s"]), 0.5 * float(det["s_minor"])
    if not all(math.isfinite(x) for x in (u, v, a, b)):
        return 0, 0
    H, W = image.shape[:2]
    u0, u1 = int(max(u - a - 4, 0)), int(min(u + a + 5, W))
    v0, v1 = int(max(v - a - 4, 0)), int(min(v + a + 5, H))
    if u1 <= u0 or v1 <= v0:
        return 0, 0
    vv, uu = np.mgrid[v0:v1, u0:u1]
    r = np.hypot(uu - u, vv - v)
    band = (r >= b - 3.0) & (r <= a + 3.0)
    g = np.asarray(image)[v0:v1, u0:u1][band].astype(float)
    return int(np.sum((g >= full) | (g <= 0))), int(g.size)
