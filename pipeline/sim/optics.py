"""Real-camera image formation for the simulator (scenario section ``[optics]``).

The renderer (:mod:`pipeline.sim.render`) gives the scene radiance on the
image as *linear grey* ``L`` (the scenario's grey levels, 0..255, 255 being the
full well at unit gain). This module turns it into the bytes a real camera
writes, each effect a knob of :class:`pipeline.sim.scenario.OpticsCfg`:

* **scene** (applied by the renderer, per point of the plate, before blur):
  uneven illumination and a specular sheen (:class:`PlateLight`);
* **optics**: thin-lens defocus, a pillbox whose radius follows the plate depth
  per pixel (:class:`Defocus`, :func:`variable_pillbox`), on top of the
  existing Gaussian blur;
* **sensor** (:func:`form_image`): vignetting, exposure gain, PRNU, shot noise,
  saturation at the full well, read noise, optionally a Bayer RGGB mosaic with
  12-bit raw values, demosaicing and white balance, then the response curve
  (:class:`Response`: linear, sRGB, gamma, an unknown seeded curve) and 8-bit
  quantisation;
* **motion**: damped vibration of the camera after each move
  (:class:`Vibration`), which the encoders do not see.

Units: lengths in metres, angles in radians, image quantities in pixels, the
sensor signal ``E`` as a fraction of the full well (0..1), electrons ``e-``,
output values in grey levels (DN, 0..255).

With every knob at its default nothing here is used and the simulator forms
images exactly as before (:func:`pipeline.sim.image_finish.finish_image`).
All randomness comes from the caller's generators, which the simulator seeds
from streams of their own (``SeedSequence(seed, spawn_key=(2000, ...))``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64, matrix_from_axis_angle

#: Response kinds of :class:`Response`.
RESPONSES = ("linear", "srgb", "gamma", "curve")
#: Demosaicing methods -> OpenCV codes for an RGGB sensor (top-left photosite red).
#: OpenCV names Bayer patterns after the second row, so ``COLOR_BayerRG2BGR`` is
#: for BGGR; the ``RGGB`` aliases are unambiguous.
DEMOSAIC = {
    "bilinear": cv2.COLOR_BayerRGGB2BGR,
    "ea": cv2.COLOR_BayerRGGB2BGR_EA,
    "vng": cv2.COLOR_BayerRGGB2BGR_VNG,
}
#: Bits of the raw (Bayer) analogue-to-digital conversion before demosaicing.
RAW_BITS = 12


# --------------------------------------------------------------------------- response
def srgb_encode(E: ArrayLike) -> F64:
    """The IEC 61966-2-1 (sRGB) transfer function, linear ``E`` -> encoded ``V``.

    ``V = 12.92 E`` for ``E <= 0.0031308``, else ``V = 1.055 E^(1/2.4) - 0.055``;
    both in 0..1. Encoded halfway grey ``V = 0.5`` is ``E = 0.214``.

    Parameters
    ----------
    E : array (any shape), clipped to 0..1

    Returns
    -------
    V : float array of the same shape
    """
    x = np.clip(np.asarray(E, dtype=float), 0.0, 1.0)
    out: F64 = np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055
    )
    return out


def draw_curve_params(rng: np.random.Generator) -> dict[str, float]:
    """Parameters of an unknown camera curve (see :meth:`Response.encode`, kind ``curve``).

    ``gamma`` U(1.7, 2.6), ``weight`` U(0.3, 0.7) of the power law against the
    filmic S-curve, S-curve ``contrast`` U(4, 8) and ``pivot`` U(0.35, 0.6).
    Four draws, in that order.
    """
    return {
        "gamma": float(rng.uniform(1.7, 2.6)),
        "weight": float(rng.uniform(0.3, 0.7)),
        "contrast": float(rng.uniform(4.0, 8.0)),
        "pivot": float(rng.uniform(0.35, 0.6)),
    }


@dataclass(frozen=True)
class Response:
    """The camera's response (opto-electronic transfer) curve ``V = f(E)``, 0..1 -> 0..1.

    Attributes
    ----------
    kind : ``linear`` | ``srgb`` | ``gamma`` | ``curve``
        ``linear``: ``V = E``. ``srgb``: :func:`srgb_encode`. ``gamma``:
        ``V = E^(1/gamma)``. ``curve``: an unknown smooth monotone curve, a mix
        of a power law and a filmic S-curve,

            x = E^(1/g),  L(x) = 1 / (1 + exp(-c (x - m))),
            V = w x + (1 - w) (L(x) - L(0)) / (L(1) - L(0)),

        with ``g, w, c, m`` = ``params`` gamma, weight, contrast, pivot
        (:func:`draw_curve_params`); strictly increasing, ``f(0) = 0``, ``f(1) = 1``.
    gamma : float
        Exponent of ``gamma``.
    params : tuple of (name, value)
        Parameters of ``curve``.
    """

    kind: str = "linear"
    gamma: float = 2.2
    params: tuple[tuple[str, float], ...] = ()

    def encode(self, E: ArrayLike) -> F64:
        """Encoded value ``V`` (0..1) of the signal ``E`` (fraction of full well, clipped to 0..1)."""
        x = np.clip(np.asarray(E, dtype=float), 0.0, 1.0)
        if self.kind == "linear":
            return x
        if self.kind == "srgb":
            return srgb_encode(x)
        if self.kind == "gamma":
            out: F64 = np.power(x, 1.0 / self.gamma)
            return out
        if self.kind == "curve":
            p = dict(self.params)
            xg = np.power(x, 1.0 / p["gamma"])
            c, m, w = p["contrast"], p["pivot"], p["weight"]

            def logistic(t: Any) -> Any:
                return 1.0 / (1.0 + np.exp(-c * (t - m)))

            s = (logistic(xg) - logistic(0.0)) / (logistic(1.0) - logistic(0.0))
            res: F64 = w * xg + (1.0 - w) * s
            return res
        raise ValueError(f"unknown response {self.kind!r} (known: {', '.join(RESPONSES)})")

    def table(self) -> list[float]:
        """256 entries: encoded grey ``255 f(i / 255)`` for linear grey ``i`` = 0..255."""
        v = 255.0 * self.encode(np.arange(256) / 255.0)
        return [round(float(x), 4) for x in v]


# --------------------------------------------------------------------------- defocus
@dataclass(frozen=True)
class Defocus:
    """Thin-lens defocus: a pillbox (disc) PSF whose radius follows the depth.

    A point at depth ``z`` (m, along the optical axis) focused by a lens of
    entrance-pupil diameter ``A`` set for ``z_f`` images as a disc of diameter
    ``c = A v_f |1/z - 1/z_f|`` on the sensor (``v_f`` the lens-sensor
    distance). In pixels, with ``f_px = v_f / pitch``:

        r_px(z) = k |1/z - 1/z_f|,   k = A f_px / 2   (px m)

    Attributes
    ----------
    k_px_m : float
        ``A f_px / 2`` (px m).
    focus_m : float
        Focus distance ``z_f`` (m).
    """

    k_px_m: float
    focus_m: float

    def radius_px(self, z: ArrayLike) -> F64:
        """Circle-of-confusion radius (px) at depth ``z`` (m); ``z <= 0`` (no plane) -> at infinity."""
        zz = np.asarray(z, dtype=float)
        inv = np.where(zz > 0, 1.0 / np.where(zz > 0, zz, 1.0), 0.0)
        out: F64 = self.k_px_m * np.abs(inv - 1.0 / self.focus_m)
        return out


def pillbox_kernel(radius: float, subsamples: int = 16) -> F64:
    """Normalised disc kernel of ``radius`` cells by area coverage, ``(2n+1, 2n+1)``.

    Each cell's weight is the fraction of its ``subsamples x subsamples``
    points inside the disc, the kernel then divided by its sum (a uniform field
    keeps its level). ``radius`` below 1e-6 gives the identity ``[[1]]``.
    """
    if radius < 1e-6:
        return np.ones((1, 1))
    n = int(np.ceil(radius + 0.5))
    off = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    c = np.arange(-n, n + 1)
    x = (c[:, None] + off[None, :]).ravel()
    xx, yy = np.meshgrid(x, x)
    inside = (xx * xx + yy * yy <= radius * radius).astype(float)
    m = 2 * n + 1
    k = inside.reshape(m, subsamples, m, subsamples).mean(axis=(1, 3))
    if k.sum() <= 0:
        return np.ones((1, 1))
    out: F64 = k / k.sum()
    return out


def variable_pillbox(img: F64, radius: F64, step: float = 0.25) -> F64:
    """Blur ``img`` with a pillbox whose radius varies per pixel (``radius``, cells).

    The image is blurred with pillboxes of radii ``0, step, 2 step, ...``
    spanning the radius map, and each pixel takes the linear blend of the two
    copies bracketing its own radius (a gather approximation of the
    space-variant PSF, exact where the radius is constant on the kernel's
    support).

    Parameters
    ----------
    img : (H, W) float
    radius : (H, W) float, cells (pixels of ``img``)
    step : float
        Spacing of the precomputed radii (cells).

    Returns
    -------
    (H, W) float
    """
    r = np.asarray(radius, dtype=float)
    rmax = float(np.max(r))
    if rmax < 1e-6:
        return np.asarray(img, dtype=float)
    pos = r / step
    j0 = int(np.floor(float(np.min(pos))))
    j1 = max(int(np.ceil(rmax / step)), j0 + 1)
    copies = np.stack(
        [
            cv2.filter2D(
                np.asarray(img, dtype=float),
                -1,
                pillbox_kernel(j * step),
                borderType=cv2.BORDER_REPLICATE,
            )
            for j in range(j0, j1 + 1)
        ]
    )
    jl = np.clip(np.floor(pos).astype(int), j0, j1 - 1)
    w = np.clip(pos - jl, 0.0, 1.0)
    i = jl - j0
    lo = np.take_along_axis(copies, i[None], axis=0)[0]
    hi = np.take_along_axis(copies, (i + 1)[None], axis=0)[0]
    out: F64 = (1.0 - w) * lo + w * hi
    return out


# --------------------------------------------------------------------------- illumination
@dataclass(frozen=True)
class PlateLight:
    """Irradiance on the plate: a linear gradient fixed to the plate, and a specular sheen.

    The radiance of a plate point ``(x, y)`` (plate frame, m) of diffuse grey
    ``g`` seen from the camera is

        L = (1 + gx x + gy y) (g + h exp(-theta^2 / (2 w^2)))

    ``(gx, gy)`` (1/m) the illumination gradient: with fraction ``f`` across the
    plate diameter ``2 R_p`` in direction ``beta``, ``(gx, gy) = f / (2 R_p)
    (cos beta, sin beta)`` (from ``1 - f/2`` to ``1 + f/2`` across the plate;
    it moves with the target in the image). The sheen is the broad specular lobe
    of a light at the camera (ring light): ``theta`` is the angle between the
    plate normal and the direction from the point to the camera, ``h`` (grey)
    the peak, ``w`` the lobe width.

    Attributes
    ----------
    gradient_per_m : (gx, gy), 1/m
    sheen_grey : float
        ``h``, linear grey at the lobe's peak.
    sheen_width_rad : float
        ``w``.
    """

    gradient_per_m: tuple[float, float] = (0.0, 0.0)
    sheen_grey: float = 0.0
    sheen_width_rad: float = 0.26

    def radiance(self, grey: float, xy: F64, ok: np.ndarray, T_camera_target: F64) -> F64:
        """Radiance ``L`` (linear grey) of plate points of diffuse grey ``grey``.

        Parameters
        ----------
        grey : float
        xy : (..., 2) plate coordinates (m)
        ok : (...) bool, the ray hit the plate (elsewhere ``grey`` is returned)
        T_camera_target : (4, 4)

        Returns
        -------
        (...) float
        """
        x = np.where(ok, xy[..., 0], 0.0)
        y = np.where(ok, xy[..., 1], 0.0)
        illum = 1.0 + self.gradient_per_m[0] * x + self.gradient_per_m[1] * y
        val = np.full(x.shape, float(grey))
        if self.sheen_grey:
            R = T_camera_target[:3, :3]
            t = T_camera_target[:3, 3]
            px = R[0, 0] * x + R[0, 1] * y + t[0]
            py = R[1, 0] * x + R[1, 1] * y + t[1]
            pz = R[2, 0] * x + R[2, 1] * y + t[2]
            dist = np.sqrt(px * px + py * py + pz * pz)
            cos_t = -(R[0, 2] * px + R[1, 2] * py + R[2, 2] * pz) / np.maximum(dist, 1e-12)
            theta = np.arccos(np.clip(cos_t, -1.0, 1.0))
            val = val + self.sheen_grey * np.exp(-0.5 * (theta / self.sheen_width_rad) ** 2)
        out: F64 = np.where(ok, illum * val, float(grey))
        return out


# --------------------------------------------------------------------------- vibration
@dataclass(frozen=True)
class Vibration:
    """Damped oscillation of the camera after a move ends (the encoders do not see it).

    With ``dt = t - t_end`` (s) the time since the end of the last move, the
    camera frame is displaced by

        d(t) = a e^(-dt / tau) sin(2 pi f dt + phi) u        (m, camera frame)
        theta(t) = a_rot e^(-dt / tau) sin(2 pi f dt + phi)  (rad, about w)

    for ``dt >= 0`` (nothing during the move): ``T_base_camera' = T_base_camera
    Trans(d) Rot(w, theta)``. Per move the unit vectors ``u``, ``w`` and the
    phase ``phi`` (the oscillation's phase when the commanded motion stops) are
    drawn (:meth:`draw`); the amplitude is the same for every move.

    Attributes
    ----------
    amplitude_m, amplitude_rad : float
        ``a`` (m), ``a_rot`` (rad).
    freq_hz : float
        ``f``.
    damping_s : float
        ``tau``, the time constant of the envelope.
    """

    amplitude_m: float = 0.0
    amplitude_rad: float = 0.0
    freq_hz: float = 15.0
    damping_s: float = 0.3

    @property
    def active(self) -> bool:
        return self.amplitude_m > 0 or self.amplitude_rad > 0

    @staticmethod
    def draw(rng: np.random.Generator) -> tuple[F64, F64, float]:
        """Direction ``u`` (3,), rotation axis ``w`` (3,) and phase ``phi`` of one move."""
        u = rng.normal(size=3)
        w = rng.normal(size=3)
        phi = float(rng.uniform(0.0, 2.0 * np.pi))
        return u / np.linalg.norm(u), w / np.linalg.norm(w), phi

    def envelope(self, dt_s: float, phase: float) -> float:
        """``e^(-dt/tau) sin(2 pi f dt + phi)`` for ``dt >= 0``, else 0."""
        if dt_s < 0:
            return 0.0
        return float(
            np.exp(-dt_s / self.damping_s) * np.sin(2.0 * np.pi * self.freq_hz * dt_s + phase)
        )

    def transform(self, dt_s: float, draw: tuple[F64, F64, float]) -> F64:
        """``Trans(d(t)) Rot(w, theta(t))`` (4, 4): the camera's motion in its own frame."""
        u, w, phi = draw
        s = self.envelope(dt_s, phi)
        T = np.eye(4)
        if self.amplitude_rad > 0:
            T[:3, :3] = matrix_from_axis_angle(w, self.amplitude_rad * s)
        T[:3, 3] = self.amplitude_m * s * u
        return T


# --------------------------------------------------------------------------- sensor
@dataclass(frozen=True, eq=False)
class Sensor:
    """The sensor and its processing (:func:`form_image`).

    Attributes
    ----------
    response : Response
    gain : float
        Exposure gain: ``E = gain L / 255`` (fraction of the full well).
    shot_noise : bool
        Poisson photo-electrons.
    full_well_e : float
        Full-well capacity (e-); ``E = 1`` is this many electrons.
    read_noise_e : float
        Read noise sigma (e-), added after the full-well clip.
    prnu : (H, W) float or None
        Per-pixel gain map (photo-response non-uniformity), fixed for the camera.
    bayer : bool
        RGGB colour filter mosaic, demosaiced (output BGR).
    demosaic : ``bilinear`` | ``ea`` | ``vng``
    bayer_sensitivity : (R, G, B)
        Relative response of the three filters to the (neutral) scene; white
        balance divides them out again after demosaicing.
    noise_sigma : float
        Additive noise of ``noise_sigma`` grey levels (per channel): the simulator's
        ``[camera] noise_sigma``.
    noise_domain : ``sensor`` | ``output``
        Where it enters: ``sensor``, on the signal before the response curve
        (``noise_sigma / 255`` of the full scale, as read noise does); ``output``, on
        the encoded grey levels. The same for a linear response.
    vignetting : float
        ``1 - v (r / r_corner)^2`` on the irradiance.
    """

    response: Response = field(default_factory=Response)
    gain: float = 1.0
    shot_noise: bool = False
    full_well_e: float = 10000.0
    read_noise_e: float = 0.0
    prnu: np.ndarray | None = None
    bayer: bool = False
    demosaic: str = "bilinear"
    bayer_sensitivity: tuple[float, float, float] = (0.55, 1.0, 0.45)
    noise_sigma: float = 2.0
    noise_domain: str = "sensor"
    vignetting: float = 0.15


def prnu_map(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> F64:
    """PRNU gain map ``1 + sigma N(0, 1)`` of ``shape`` (one draw per pixel, row-major)."""
    out: F64 = 1.0 + sigma * rng.standard_normal(shape)
    return out


def bayer_channels(shape: tuple[int, int]) -> np.ndarray:
    """Channel index (0 R, 1 G, 2 B) of every photosite of an RGGB mosaic, ``(H, W)`` int."""
    ch = np.ones(shape, dtype=int)
    ch[0::2, 0::2] = 0
    ch[1::2, 1::2] = 2
    return ch


def vignette(shape: tuple[int, int], cx: float, cy: float, v: float) -> F64:
    """Irradiance factor ``1 - v (r / r_corner)^2``, ``r`` from the principal point ``(cx, cy)``."""
    H, W = shape
    vv, uu = np.mgrid[0:H, 0:W].astype(float)
    r2 = (uu - cx) ** 2 + (vv - cy) ** 2
    r2max = max(cx, W - 1 - cx) ** 2 + max(cy, H - 1 - cy) ** 2
    out: F64 = 1.0 - v * r2 / r2max
    return out


def form_image(
    irradiance: F64,
    sensor: Sensor,
    *,
    principal_point: tuple[float, float],
    rng_noise: np.random.Generator,
    rng_optics: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Sensor and processing: linear grey irradiance -> the camera's 8-bit image.

    1. vignetting: ``L <- L (1 - v (r / r_corner)^2)``;
    2. exposure: ``E = gain L / 255`` (fraction of the full well); with Bayer,
       times the filter's sensitivity at each photosite (RGGB);
    3. PRNU: ``E <- E p(u, v)``;
    4. electrons ``n = E N_fw``, Poisson if ``shot_noise`` (variance = mean, in e-);
    5. saturation: ``n <- min(n, N_fw)`` (the full well);
    6. read noise: ``n <- n + N(0, sigma_read^2)``; ``E = n / N_fw``;
    7. Bayer: 12-bit raw ``rint(E 4095)``, demosaicing (OpenCV, RGGB), white
       balance (divide by the sensitivities);
    8. ``E`` clipped to 0..1, response ``V = f(E)``, ``DN = 255 V + N(0, noise_sigma^2)``,
       ``rint``, clipped to ``uint8``; with ``noise_domain = "sensor"`` and a response
       that is not linear, the same draw ``n`` enters before the curve instead:
       ``DN = 255 f(clip(E + n / 255, 0, 1))``. Behind a curve of slope ``f'`` the
       output-domain noise seen on the signal is ``1 / f'`` times larger where the
       curve is flat (``bench_noise_placement.py``); a camera's noise is its sensor's.

    Parameters
    ----------
    irradiance : (H, W) float
        Linear grey (0..255 at unit gain), blurred, before vignetting.
    sensor : Sensor
    principal_point : (cx, cy), px
        Centre of the vignetting.
    rng_noise : Generator
        Source of the additive noise of step 8 (``noise_sigma``).
    rng_optics : Generator
        Source of shot and read noise.

    Returns
    -------
    image : (H, W) uint8, or (H, W, 3) uint8 BGR with Bayer
    grey : (H, W) uint8
        What a controller detects on (``cv2.COLOR_BGR2GRAY`` of a colour image).
    """
    L = np.asarray(irradiance, dtype=float)
    shape = (L.shape[0], L.shape[1])
    if sensor.vignetting:
        L = L * vignette(shape, principal_point[0], principal_point[1], sensor.vignetting)
    E = sensor.gain * L / 255.0
    sens = np.asarray(sensor.bayer_sensitivity, dtype=float)
    if sensor.bayer:
        E = E * sens[bayer_channels(shape)]
    if sensor.prnu is not None:
        E = E * sensor.prnu
    fw = float(sensor.full_well_e)
    n_e = np.maximum(E, 0.0) * fw
    if sensor.shot_noise:
        n_e = rng_optics.poisson(n_e).astype(float)
    n_e = np.minimum(n_e, fw)
    if sensor.read_noise_e > 0:
        n_e = n_e + rng_optics.normal(0.0, sensor.read_noise_e, size=n_e.shape)
    E = n_e / fw
    if sensor.bayer:
        full = float(2**RAW_BITS - 1)
        raw = np.clip(np.rint(E * full), 0, full).astype(np.uint16)
        code = DEMOSAIC[sensor.demosaic]
        if sensor.demosaic == "vng":  # OpenCV's VNG takes 8-bit input only
            bgr = cv2.cvtColor((raw >> (RAW_BITS - 8)).astype(np.uint8), code) / 255.0
        else:
            bgr = cv2.cvtColor(raw, code) / full
        E = bgr / sens[::-1]  # white balance (BGR order)
    before = sensor.noise_domain == "sensor" and sensor.response.kind != "linear"
    n = rng_noise.normal(0.0, sensor.noise_sigma, size=E.shape) if sensor.noise_sigma > 0 else None
    if n is not None and before:
        dn = 255.0 * sensor.response.encode(np.clip(E + n / 255.0, 0.0, 1.0))
    else:
        dn = 255.0 * sensor.response.encode(np.clip(E, 0.0, 1.0))
        if n is not None:
            dn = dn + n
    out = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    grey = cv2.cvtColor(out, cv2.COLOR_BGR2GRAY) if out.ndim == 3 else out
    return out, grey


# --------------------------------------------------------------------------- print
def draw_print(
    rng: np.random.Generator,
    diameter_m: float,
    *,
    out_of_round_um: float = 0.0,
    roughness_um: float = 0.0,
    harmonics: int = 6,
    scale_error: float = 0.0,
    diameter_sigma_um: float = 0.0,
) -> dict[str, Any]:
    """One printed target's shape (parameters of :class:`pipeline.sim.target_geometry.PrintShape`).

    Draws, always in this order and number (so a knob changes no other draw):
    orientation ``phi`` U(0, pi), a diameter deviate ``z`` N(0, 1), the
    illumination direction ``beta`` U(0, 2 pi) (used by the caller), then 16
    candidate harmonics (orders a permutation of 3..40, weights U(0.2, 1),
    phases U(0, 2 pi)) of which the first ``harmonics`` are used.

    * printed (mean) diameter ``D_p = D (1 + scale_error) + sigma z``;
    * out of round: an ellipse of semi-axes ``R (1 + e)``, ``R (1 - e)``,
      ``R = D_p / 2``, ``e = delta / (4 R)`` for a diameter difference ``delta``
      (``out_of_round_um``), long axis at ``phi`` in the plate frame; its mean
      diameter stays ``D_p``;
    * edge roughness: ``r(phi) += sum_k A_k cos(k phi + p_k)``, orders ``k >= 3``
      (no shift of the centre, no ellipticity), amplitudes scaled so that the RMS
      radius deviation ``sqrt(sum A_k^2 / 2)`` is ``roughness_um``.

    Returns
    -------
    dict with ``diameter_m`` (D_p), ``radius_m``, ``ellipticity``,
    ``orientation_rad``, ``semi_axes_m``, ``harmonics`` (list of [k, A_k m, p_k]),
    ``roughness_rms_m``, ``illumination_direction_rad``.
    """
    phi = float(rng.uniform(0.0, np.pi))
    z = float(rng.normal())
    beta = float(rng.uniform(0.0, 2.0 * np.pi))
    ks = rng.permutation(np.arange(3, 41))[:16]
    wts = rng.uniform(0.2, 1.0, 16)
    phases = rng.uniform(0.0, 2.0 * np.pi, 16)
    d_p = diameter_m * (1.0 + scale_error) + diameter_sigma_um * 1e-6 * z
    if scale_error == 0.0 and diameter_sigma_um == 0.0:
        d_p = diameter_m
    R = 0.5 * d_p
    e = out_of_round_um * 1e-6 / (4.0 * R)
    hs: list[list[float]] = []
    n = max(0, min(int(harmonics), 16))
    if roughness_um > 0 and n > 0:
        w = wts[:n]
        amp = w * (roughness_um * 1e-6) / np.sqrt(np.sum(w * w) / 2.0)
        hs = [[int(k), float(a), float(p)] for k, a, p in zip(ks[:n], amp, phases[:n], strict=True)]
    return {
        "diameter_m": float(d_p),
        "radius_m": float(R),
        "ellipticity": float(e),
        "orientation_rad": phi,
        "semi_axes_m": [float(R * (1 + e)), float(R * (1 - e))],
        "harmonics": hs,
        "roughness_rms_m": float(np.sqrt(sum(h[1] ** 2 for h in hs) / 2.0)),
        "illumination_direction_rad": beta,
    }
