"""A second image source the team did not write: captures rendered by Mitsuba 3 (``[render]`` extra).

:class:`PbrSource` forms one capture of the simulated cell with a physically
based renderer (Mitsuba 3, ``scalar_rgb`` variant, CPU) instead of the
simulator's own area-coverage renderer (:mod:`pipeline.sim.render`). The
simulator calls it through its image-source hook (:attr:`pipeline.sim.session.Session.image_source`),
so the touch-up loop drives the robot and this renderer forms every image the
loop and the recording see. Nothing of :mod:`pipeline.sim.render`,
:mod:`pipeline.sim.optics` or :mod:`pipeline.sim.image_finish` is used.

The scene (target plate frame ``z = 0``, normal ``+z``; fixed in the world)
    *Plate*: a disk of ``plate_radius_m``; *print*: a square decal 3 um above it
    carrying the printed disc as a bitmap texture (6.3 um texels). Both share one
    BSDF, ``blendbsdf`` of a ``diffuse`` (the texture) and, with the ``sheen``
    effect, a ``roughconductor`` (GGX, ``alpha`` 0.35, weight ``w``): a slightly
    specular plate whose highlight of the lamp moves with the camera pose.
    *Lamp*: with ``uneven_light`` a ``spot`` fixed in the world, 0.4 m from the
    target at 35 deg from its normal, aimed so that the target lies in the
    beam's edge (Mitsuba's linear fall-off between ``beam_width`` 8 deg and
    ``cutoff_angle`` 28 deg) with an irradiance change of ``g`` over the target's
    diameter (drawn U(0.10, 0.20) per target); else a ``directional`` lamp
    (even irradiance). *Background*: an evenly glowing wall 50 mm behind the
    plate (0.85 x the white print's radiance at the target centre behind light
    plates, 1.5 x the dark plate's behind dark ones, as the simulator's scenes have).
    *Print*: boundary ``r(phi) = R + sum_{k=2..5} A_k cos(k phi + p_k)`` (out of
    round: peak-to-valley of ``r - R`` drawn U(10, 20) um per target), reflectance
    ``Phi((r(phi) - r) / sigma)`` between ink and paper. Ink spread: ``sigma`` 10 um
    (else half a texel); the artwork is taken to compensate the ink's mean growth,
    so the printed diameter is the declared one (a growth common to every print
    cannot be told from the pin, ``docs/simulator.md``; it would put an error of
    growth / radius x stand-off into the truth that no method can remove).

The camera
    Thin lens (``thinlens``) at the capture pose, aperture radius ``A`` and focus
    distance ``F``: a point at depth ``z`` spreads to a disc of radius
    ``fx A |1/z - 1/F|`` px. With ``defocus`` ``F = z0 + dF`` (``|dF|`` U(10, 20) mm,
    random sign; ``z0`` the stand-off) and ``A`` set so that the radius at ``z0``
    is U(0.5, 1.5) px; else a pinhole (``perspective``). Mitsuba's film has its
    principal point at the image centre and no distortion, so the render is
    resampled (``cv2.remap``, bilinear) onto the simulator's camera model
    (principal point, ``k1``, ``k2``): the whole frame rendered at half the
    resolution (4 samples per pixel; it carries the plate's light and rim, not the
    target), and the target's box (its image plus 6 px) on a 2x finer grid at 16
    samples per pixel, each output pixel the mean of its 2 x 2 resampled sub-pixels
    (Monte Carlo noise there 0.5 grey RMS against the sensor's 1.5, linear grey).

The sensor (after the renderer; each effect a switch of :class:`PbrEffects`)
    ``E = gain L`` (fraction of the full well; the gain puts the white print at
    the target centre at 160/255, so that the brighter side of the lit plate does not
    saturate), ``E <- E (1 + prnu)`` (1 % PRNU, a fixed
    map per seed), electrons ``Poisson(E Nfw) + N(0, read^2)`` (``Nfw`` 10 000 e-,
    read noise 8 e-), the response (sRGB, IEC 61966-2-1:
    ``V = 12.92 E`` for ``E <= 0.0031308`` else ``1.055 E^(1/2.4) - 0.055``; or
    linear ``V = E``), ``DN = round(255 V)`` in ``uint8``, then JPEG quality 90
    (``cv2.imencode``; the session records the JPEG bytes, the controller sees
    the decoded image).

Random streams: ``SeedSequence(seed, spawn_key=(3000, ...))``: ``(3000, 0)`` the
world (lens, prints, lamps, PRNU), ``(3000, 1, k)`` capture ``k``'s noise and
Mitsuba's sampler seed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields
from typing import Any

import cv2
import numpy as np
from scipy.special import ndtr

from pipeline.kinematics.se3 import F64, invert_transform
from pipeline.sim.camera import CameraModel
from pipeline.sim.scenario import Scenario
from pipeline.sim.target_geometry import PrintShape

#: Mitsuba camera axes (x left, y up, z forward) from OpenCV's (x right, y down, z forward)
CV_TO_MI = np.diag([-1.0, -1.0, 1.0, 1.0])
TEXELS = 2048
LAMP_DISTANCE_M = 0.4
LAMP_ELEVATION_RAD = np.radians(35.0)
BEAM_WIDTH_DEG, CUTOFF_DEG = 8.0, 28.0
SHEEN_ALPHA = 0.35
WHITE_DN = 160.0
REFLECTANCE_WHITE = 0.8


@dataclass(frozen=True)
class PbrEffects:
    """Which effects the capture has (each switchable)."""

    defocus: bool = True
    uneven_light: bool = True
    sheen: bool = True
    out_of_round: bool = True
    ink_spread: bool = True
    shot_noise: bool = True
    read_noise: bool = True
    prnu: bool = True
    srgb: bool = True
    jpeg: bool = True

    @classmethod
    def linear(cls) -> PbrEffects:
        """The twin: no sRGB, no JPEG, in focus, even light, round print (sensor noise kept)."""
        return cls(
            defocus=False,
            uneven_light=False,
            sheen=False,
            out_of_round=False,
            ink_spread=False,
            srgb=False,
            jpeg=False,
        )

    @classmethod
    def only(cls, *names: str) -> PbrEffects:
        """The linear twin plus the named effects."""
        return cls(**{**asdict(cls.linear()), **dict.fromkeys(names, True)})

    def names(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name)]


@dataclass(frozen=True)
class PbrSettings:
    """Sampling and sensor constants."""

    frame_scale: float = 0.5
    spp_frame: int = 4
    spp_box: int = 16
    box_scale: int = 2
    full_well_e: float = 10000.0
    read_noise_e: float = 8.0
    prnu_sigma: float = 0.01
    jpeg_quality: int = 90


def srgb(E: F64) -> F64:
    """IEC 61966-2-1 encoding of linear ``E`` in 0..1 (see module doc)."""
    x = np.clip(E, 0.0, 1.0)
    out: F64 = np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055
    )
    return out


def _mi() -> Any:
    import mitsuba as mi

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


class PbrSource:
    """The image source: ``source(target, Ts, options) -> (image, grey)`` for one session.

    Parameters
    ----------
    camera : CameraModel
        The simulator's intrinsics (the render is resampled onto them).
    targets : list of (id, T_base_target (4, 4))
    diameter_m, plate_radius_m : float
    polarity : str
        ``dark_on_light`` or ``light_on_dark``.
    standoff_m : float
        Camera-to-target distance at convergence (the focus is set against it).
    seed : int
    effects : PbrEffects
    settings : PbrSettings
    """

    def __init__(
        self,
        camera: CameraModel,
        targets: list[tuple[int, F64]],
        diameter_m: float,
        plate_radius_m: float,
        polarity: str,
        standoff_m: float,
        seed: int,
        effects: PbrEffects | None = None,
        settings: PbrSettings | None = None,
    ) -> None:
        self.cam = camera
        self.D, self.R_plate = diameter_m, plate_radius_m
        self.polarity = polarity
        self.seed = seed
        self.eff = effects or PbrEffects()
        self.cfg = settings or PbrSettings()
        self.captures = 0
        self.render_s = 0.0
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(3000, 0)))
        dF = float(rng.uniform(0.010, 0.020)) * float(rng.choice([-1.0, 1.0]))
        r0 = float(rng.uniform(0.5, 1.5))
        self.focus_m = standoff_m + dF
        self.aperture_m = r0 / (camera.fx * abs(1.0 / standoff_m - 1.0 / self.focus_m))
        self.defocus_px_at_standoff = r0
        self.world: dict[int, dict[str, Any]] = {}
        for tid, _ in targets:
            self.world[tid] = self._draw_target(rng)
        self.prnu = rng.normal(0.0, self.cfg.prnu_sigma, (camera.height, camera.width))
        self._scenes: dict[int, tuple[Any, float]] = {}
        self._maps = _frame_maps(camera, self.cfg.frame_scale)

    # ------------------------------------------------------------------ world
    def _draw_target(self, rng: np.random.Generator) -> dict[str, Any]:
        """One target's print and lamp (always the same draws, whatever the switches)."""
        ks = np.arange(2, 6)
        w = rng.uniform(0.2, 1.0, 4)
        ph = rng.uniform(0.0, 2 * np.pi, 4)
        ptv = float(rng.uniform(10e-6, 20e-6))
        phi = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
        dev = (w[:, None] * np.cos(ks[:, None] * phi[None] + ph[:, None])).sum(0)
        amp = w * ptv / (dev.max() - dev.min())
        grad = float(rng.uniform(0.10, 0.20))
        azimuth = float(rng.uniform(0.0, 2 * np.pi))
        return {
            "harmonics": [
                [int(k), float(a), float(p)] for k, a, p in zip(ks, amp, ph, strict=True)
            ],
            "out_of_round_ptv_m": ptv,
            "ink_sigma_m": 10e-6,
            "light_gradient": grad,
            "lamp_azimuth_rad": azimuth,
            "sheen_weight": 0.024,
        }

    def print_radius(self, tid: int, phi: F64) -> F64:
        """Printed boundary radius ``r(phi)`` (m) of target ``tid`` as rendered."""
        wt = self.world[tid]
        r = np.full_like(np.asarray(phi, dtype=float), 0.5 * self.D)
        if self.eff.out_of_round:
            for k, a, p in wt["harmonics"]:
                r = r + a * np.cos(k * phi + p)
        return r

    def _texture(self, tid: int) -> tuple[F64, float]:
        """The decal's reflectance bitmap (TEXELS^2) and its half side (m)."""
        half = 0.5 * self.D + 1.5e-3
        texel = 2 * half / TEXELS
        c = (np.arange(TEXELS) + 0.5) * texel - half
        x, y = np.meshgrid(c, c)  # row 0 at y = -half (checked: the rendered long axis)
        r, phi = np.hypot(x, y), np.arctan2(y, x)
        sigma = self.world[tid]["ink_sigma_m"] if self.eff.ink_spread else 0.5 * texel
        inside = ndtr((self.print_radius(tid, phi) - r) / sigma)
        ink, paper = self._reflectances()
        disc, plate = (ink, paper) if self.polarity == "dark_on_light" else (paper, ink)
        return plate + (disc - plate) * inside, half

    def _reflectances(self) -> tuple[float, float]:
        return 0.2 * REFLECTANCE_WHITE, REFLECTANCE_WHITE

    def _lamp(self, tid: int, mi: Any) -> dict[str, Any]:
        """The lamp (fixed in the target frame, so in the world)."""
        wt = self.world[tid]
        if not self.eff.uneven_light:
            d = np.array([np.sin(LAMP_ELEVATION_RAD), 0.0, np.cos(LAMP_ELEVATION_RAD)])
            return {"type": "directional", "direction": (-d).tolist(), "irradiance": 1.0}
        az = wt["lamp_azimuth_rad"]
        pos = LAMP_DISTANCE_M * np.array(
            [
                np.sin(LAMP_ELEVATION_RAD) * np.cos(az),
                np.sin(LAMP_ELEVATION_RAD) * np.sin(az),
                np.cos(LAMP_ELEVATION_RAD),
            ]
        )
        aim = _aim_for_gradient(pos, wt["light_gradient"], 0.5 * self.D, az)
        T = mi.ScalarTransform4f
        return {
            "type": "spot",
            "to_world": T.look_at(origin=pos.tolist(), target=aim.tolist(), up=[0, 0, 1]),
            "intensity": {"type": "spectrum", "value": 1.0},
            "beam_width": BEAM_WIDTH_DEG,
            "cutoff_angle": CUTOFF_DEG,
        }

    def _scene(self, tid: int) -> tuple[Any, float]:
        """The Mitsuba scene of target ``tid`` and its gain (cached)."""
        if tid in self._scenes:
            return self._scenes[tid]
        mi = _mi()
        T = mi.ScalarTransform4f
        tex, half = self._texture(tid)
        ink, paper = self._reflectances()
        plate_rho = paper if self.polarity == "dark_on_light" else ink
        bg_rho = 0.85 * paper if self.polarity == "dark_on_light" else 1.5 * ink
        w_s = self.world[tid]["sheen_weight"] if self.eff.sheen else 0.0

        def bsdf(refl: Any) -> dict[str, Any]:
            diffuse = {"type": "diffuse", "reflectance": refl}
            if w_s == 0.0:
                return diffuse
            spec = {"type": "roughconductor", "material": "none", "alpha": SHEEN_ALPHA}
            return {"type": "blendbsdf", "weight": w_s, "bsdf_0": diffuse, "bsdf_1": spec}

        bitmap = mi.Bitmap(tex[:, :, None].astype(np.float32))
        lamp = self._lamp(tid, mi)
        # gain: the white print's diffuse radiance at the target centre -> WHITE_DN / 255
        emitter = mi.load_dict({"type": "scene", "lamp": lamp}).emitters()[0]
        it = mi.Interaction3f()
        it.p = mi.ScalarPoint3f(0.0, 0.0, 0.0)
        ds, wgt = emitter.sample_direction(it, mi.ScalarPoint2f(0.5, 0.5))
        irr = float(mi.luminance(wgt)) * max(float(ds.d[2]), 0.0)  # the film's luminance
        L_white = (1.0 - w_s) * REFLECTANCE_WHITE / np.pi * irr
        gain = WHITE_DN / 255.0 / L_white
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
                "plate": {
                    "type": "disk",
                    "to_world": T.scale(self.R_plate),
                    "bsdf": bsdf({"type": "rgb", "value": plate_rho}),
                },
                "print": {
                    "type": "rectangle",
                    "to_world": T.translate([0.0, 0.0, 3e-6]).scale([half, half, 1.0]),
                    "bsdf": bsdf({"type": "bitmap", "bitmap": bitmap, "raw": True}),
                },
                # an evenly glowing wall behind the plate (never sampled as a light)
                "background": {
                    "type": "rectangle",
                    "to_world": T.translate([0.0, 0.0, -0.05]).scale(1.0),
                    "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                    "emitter": {
                        "type": "area",
                        "radiance": {"type": "rgb", "value": bg_rho / REFLECTANCE_WHITE * L_white},
                        "sampling_weight": 0.0,
                    },
                },
                "lamp": lamp,
            }
        )
        self._scenes[tid] = (scene, gain)
        return scene, gain

    # ------------------------------------------------------------------ image
    def radiance(self, tid: int, T_camera_target: F64, seed: int) -> F64:
        """Linear sensor signal ``E`` (fraction of the full well, (H, W)) before the sensor."""
        mi = _mi()
        scene, gain = self._scene(tid)
        cam = self.cam
        W, H = cam.width, cam.height
        to_world = mi.ScalarTransform4f(invert_transform(T_camera_target) @ CV_TO_MI)
        fs, spp = self.cfg.frame_scale, self.cfg.spp_frame
        frame = _render(mi, scene, self._sensor(mi, to_world, fs, None, spp), seed)
        img = cv2.remap(frame, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        box = self._box(T_camera_target)
        if box is not None:
            u0, u1, v0, v1 = box
            s = self.cfg.box_scale
            mx, my = _box_maps(cam, s, box)
            ox, oy = int(np.floor(mx.min())) - 2, int(np.floor(my.min())) - 2
            ox, oy = max(ox, 0), max(oy, 0)
            cw = min(int(np.ceil(mx.max())) + 3, s * W) - ox
            ch = min(int(np.ceil(my.max())) + 3, s * H) - oy
            sensor = self._sensor(mi, to_world, s, (ox, oy, cw, ch), self.cfg.spp_box)
            fine = _render(mi, scene, sensor, seed + 1)
            sub = cv2.remap(
                fine, mx - ox, my - oy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
            img[v0:v1, u0:u1] = sub.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
        out: F64 = img.astype(float) * gain
        return out

    def _sensor(
        self, mi: Any, to_world: Any, scale: float, crop: tuple[int, int, int, int] | None, spp: int
    ) -> Any:
        cam = self.cam
        W, H = int(round(scale * cam.width)), int(round(scale * cam.height))
        film: dict[str, Any] = {
            "type": "hdrfilm",
            "width": W,
            "height": H,
            "rfilter": {"type": "box"},
            "pixel_format": "luminance",
        }
        if crop is not None:
            film.update(
                crop_offset_x=crop[0],
                crop_offset_y=crop[1],
                crop_width=crop[2],
                crop_height=crop[3],
            )
        d: dict[str, Any] = {
            "type": "perspective",
            "fov": float(np.degrees(2 * np.arctan(0.5 * cam.width / cam.fx))),
            "fov_axis": "x",
            "to_world": to_world,
            "film": film,
            "sampler": {"type": "stratified", "sample_count": spp},
            "near_clip": 0.01,
        }
        if self.eff.defocus:
            d.update(type="thinlens", aperture_radius=self.aperture_m, focus_distance=self.focus_m)
        return mi.load_dict(d)

    def _box(self, T_camera_target: F64) -> tuple[int, int, int, int] | None:
        """Output pixel box ``(u0, u1, v0, v1)`` holding the target's image and its blur."""
        cam = self.cam
        phi = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        r = 0.5 * self.D + 0.2e-3
        p = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros_like(phi), np.ones_like(phi)])
        pc = (T_camera_target @ p)[:3].T
        if np.any(pc[:, 2] <= 0.02):
            return None
        uv = cam.project(pc)
        m = 6
        u0, v0 = np.floor(uv.min(axis=0)).astype(int) - m
        u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + m
        u0, v0 = max(int(u0), 0), max(int(v0), 0)
        u1, v1 = min(int(u1), cam.width), min(int(v1), cam.height)
        if u1 - u0 < 4 or v1 - v0 < 4:
            return None
        return u0, u1, v0, v1

    def sensor(self, E: F64, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``E`` -> (recorded image before JPEG, what the controller sees) as ``uint8``."""
        cfg, eff = self.cfg, self.eff
        if eff.prnu:
            E = E * (1.0 + self.prnu)
        e = np.clip(E, 0.0, None) * cfg.full_well_e
        if eff.shot_noise:
            e = rng.poisson(e).astype(float)
        if eff.read_noise:
            e = e + rng.normal(0.0, cfg.read_noise_e, e.shape)
        V = np.clip(e / cfg.full_well_e, 0.0, 1.0)
        if eff.srgb:
            V = srgb(V)
        img = np.clip(np.rint(255.0 * V), 0, 255).astype(np.uint8)
        if not eff.jpeg:
            return img, img
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        grey = np.asarray(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), dtype=np.uint8)
        return img, grey

    def capture(self, tid: int, Ts: F64) -> tuple[np.ndarray, np.ndarray]:
        """One capture of target ``tid`` over the sub-exposure poses ``Ts`` ``(K, 4, 4)``."""
        k = self.captures
        self.captures += 1
        ss = np.random.SeedSequence(self.seed, spawn_key=(3000, 1, k))
        rng = np.random.default_rng(ss)
        seed = int(ss.generate_state(1)[0] % (2**31 - 2))
        t0 = time.perf_counter()
        E = np.mean([self.radiance(tid, T, seed) for T in np.asarray(Ts)], axis=0)
        self.render_s += time.perf_counter() - t0
        return self.sensor(E, rng)

    def __call__(self, tg: Any, Ts: F64, opts: Any) -> tuple[np.ndarray, np.ndarray]:
        """:data:`pipeline.sim.session.ImageSource`: one capture of target ``tg``."""
        if opts.extra_discs or opts.occluders:
            raise ValueError("the Mitsuba image source renders no second blobs or occluders")
        return self.capture(int(tg.id), Ts)

    def print_shape(self, tid: int) -> PrintShape:
        """Target ``tid``'s rendered half-level boundary as the simulator's reference shape."""
        r = float(self.print_radius(tid, np.zeros(1))[0])
        hs: tuple[tuple[int, float, float], ...] = ()
        if self.eff.out_of_round:
            hs = tuple((int(k), float(a), float(p)) for k, a, p in self.world[tid]["harmonics"])
            r -= sum(a * np.cos(p) for _, a, p in hs)
        return PrintShape(radius_m=r, harmonics=hs)

    def truth(self) -> dict[str, Any]:
        """What the truth file records of this image source."""
        return {
            "renderer": "mitsuba3 scalar_rgb",
            "effects": self.eff.names(),
            "settings": asdict(self.cfg),
            "focus_m": self.focus_m if self.eff.defocus else None,
            "aperture_radius_m": self.aperture_m if self.eff.defocus else 0.0,
            "defocus_radius_px_at_standoff": self.defocus_px_at_standoff
            if self.eff.defocus
            else 0.0,
            "targets": {str(k): v for k, v in self.world.items()},
            "captures": self.captures,
            "render_s": self.render_s,
        }


def _aim_for_gradient(pos: F64, grad: float, radius: float, azimuth: float) -> F64:
    """Aim point of a spot at ``pos`` (target frame) so that the irradiance across the target
    changes by ``grad`` (relative to the centre's) over its diameter.

    The spot's intensity falls linearly in angle from 1 at ``BEAM_WIDTH_DEG`` to 0 at
    ``CUTOFF_DEG`` (Mitsuba's ``spot``); irradiance ``I f(theta) cos(i) / d^2``. The
    aim point slides from the target centre away from the lamp along the plate until
    the fall-off across ``(-radius, +radius)`` along the lamp's azimuth is ``grad``.
    """
    u = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])

    def irr(p: F64, aim: F64) -> float:
        axis = (aim - pos) / np.linalg.norm(aim - pos)
        d = p - pos
        dist = float(np.linalg.norm(d))
        th = np.degrees(np.arccos(np.clip(np.dot(d / dist, axis), -1, 1)))
        f = float(np.clip((CUTOFF_DEG - th) / (CUTOFF_DEG - BEAM_WIDTH_DEG), 0.0, 1.0))
        return f * max(-d[2] / dist, 0.0) / dist**2

    def change(t: float) -> float:
        aim = -t * u
        c = irr(np.zeros(3), aim)
        return abs(irr(radius * u, aim) - irr(-radius * u, aim)) / max(c, 1e-12)

    ts = np.linspace(0.0, 0.4, 801)
    ch = np.array([change(t) for t in ts])
    i = int(np.argmin(np.abs(ch - grad)))
    out: F64 = -ts[i] * u
    return out


def _frame_maps(cam: CameraModel, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps from output pixels to Mitsuba film pixels (pixel-centre coordinates)."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    return _to_film(cam, scale, u, v)


def _to_film(cam: CameraModel, scale: float, u: F64, v: F64) -> tuple[np.ndarray, np.ndarray]:
    """Output pixel ``(u, v)`` -> the undistorted, centred film of ``scale`` x the resolution.

    ``x = undistort((u - cx) / fx, (v - cy) / fy)``, film ``u_f = s fx x + (s W - 1) / 2``.
    """
    xy = cam.pixel_to_normalised(np.stack([u, v], axis=-1))
    s = scale
    mx = s * cam.fx * xy[..., 0] + 0.5 * (s * cam.width - 1)
    my = s * cam.fy * xy[..., 1] + 0.5 * (s * cam.height - 1)
    return mx.astype(np.float32), my.astype(np.float32)


def _box_maps(
    cam: CameraModel, s: int, box: tuple[int, int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Maps of the ``s x s`` sub-pixel centres of every output pixel of ``box``."""
    u0, u1, v0, v1 = box
    off = (np.arange(s) + 0.5) / s - 0.5
    uu = (np.arange(u0, u1)[:, None] + off[None]).ravel()
    vv = (np.arange(v0, v1)[:, None] + off[None]).ravel()
    U, V = np.meshgrid(uu, vv)
    return _to_film(cam, s, U, V)


def _render(mi: Any, scene: Any, sensor: Any, seed: int) -> np.ndarray:
    img = np.array(mi.render(scene, sensor=sensor, seed=seed), dtype=np.float32)
    out: np.ndarray = img[..., 0] if img.ndim == 3 else img
    return out


def pbr_scenario(
    sc: Scenario, effects: PbrEffects, settings: PbrSettings | None = None
) -> Scenario:
    """``sc`` with what the session must know of the source: JPEG recording (quality 90)
    when the effects have it, else the scenario's own image format; no simulator optics."""
    from dataclasses import replace

    from pipeline.sim.scenario import OpticsCfg

    q = (settings or PbrSettings()).jpeg_quality if effects.jpeg else 0
    return replace(sc, optics=OpticsCfg(jpeg_quality=q))


def pbr_source(effects: PbrEffects | None = None, settings: PbrSettings | None = None) -> Any:
    """A :data:`pipeline.sim.simulator.SourceFactory`: the session's :class:`PbrSource`.

    Also gives the session's truth the rendered print shapes (``true_ellipse`` of every
    image is then the printed contour's, as the simulator's own prints are).
    """

    def make(sess: Any) -> PbrSource:
        sc = sess.sc
        src = PbrSource(
            sess.cell.camera,
            [(t.id, t.T_base_target()) for t in sess.cell.targets],
            sc.targets.diameter_m,
            sc.targets.plate_radius_m,
            sc.targets.polarity,
            float(sess.cell.p_vt_camera[2]),
            sess.seed,
            effects,
            settings,
        )
        for t in sess.cell.targets:
            sess.optics.shapes[t.id] = src.print_shape(t.id)
        return src

    return make
