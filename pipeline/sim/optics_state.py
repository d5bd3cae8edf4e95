"""The real-camera state of one simulated session (scenario ``[optics]``).

:class:`OpticsState` turns :class:`pipeline.sim.scenario.OpticsCfg` into the
objects :mod:`pipeline.sim.render` and :mod:`pipeline.sim.optics` use, drawn
from random streams of their own so that switching a knob changes no other
draw of the session:

* ``SeedSequence(seed, spawn_key=(2000, 0))``: the camera and the prints (per
  target, in the cell's order, :func:`pipeline.sim.optics.draw_print`, whose
  illumination direction also orients that target's light gradient; then the
  parameters of an unknown response curve; then the PRNU map);
* ``SeedSequence(seed, spawn_key=(2000, 1, plan_index, faulted))``: per touch-up,
  shot and read noise and the vibration of every move (:meth:`reseed`, called
  where the simulator reseeds its own per-touch-up streams).

With every knob at its default :attr:`OpticsState.active` is False and the
simulator forms images exactly as before.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import cv2
import numpy as np

from pipeline.kinematics.se3 import F64, invert_transform
from pipeline.sim.camera import CameraModel
from pipeline.sim.optics import (
    Defocus,
    PlateLight,
    Response,
    Sensor,
    Vibration,
    draw_curve_params,
    draw_print,
    form_image,
    prnu_map,
)
from pipeline.sim.scenario import Scenario
from pipeline.sim.target_geometry import PrintShape


class OpticsState:
    """Prints, lights, lens, sensor and vibration of one session.

    Parameters
    ----------
    sc : Scenario
    seed : int
    target_ids : list of int
        The cell's targets in order (one print and one light each).
    camera : CameraModel
    standoff_m : float
        Camera-to-target distance at convergence (sets the defocus scale).
    """

    def __init__(
        self,
        sc: Scenario,
        seed: int,
        target_ids: list[int],
        camera: CameraModel,
        standoff_m: float,
    ) -> None:
        op = sc.optics
        self.cfg = op
        self.seed = seed
        self.active = op.any()
        self.camera = camera
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2000, 0)))
        self.prints: dict[int, dict[str, Any]] = {}
        self.shapes: dict[int, PrintShape | None] = {}
        self.lights: dict[int, PlateLight | None] = {}
        D = sc.targets.diameter_m
        R_plate = sc.targets.plate_radius_m
        for tid in target_ids:
            pr = draw_print(
                rng,
                D,
                out_of_round_um=op.out_of_round_um,
                roughness_um=op.roughness_um,
                scale_error=op.diameter_scale_error,
                diameter_sigma_um=op.diameter_sigma_um,
            )
            self.prints[tid] = pr
            self.shapes[tid] = PrintShape.from_dict(pr) if op.print_active() else None
            if op.illumination > 0 or op.sheen_grey > 0:
                b = pr["illumination_direction_rad"]
                g = op.illumination / (2.0 * R_plate)
                self.lights[tid] = PlateLight(
                    gradient_per_m=(g * float(np.cos(b)), g * float(np.sin(b))),
                    sheen_grey=op.sheen_grey,
                    sheen_width_rad=op.sheen_width_rad,
                )
            else:
                self.lights[tid] = None
        curve = draw_curve_params(rng)
        if op.response == "curve":
            response = Response("curve", params=tuple(sorted(curve.items())))
        else:
            response = Response(op.response, gamma=op.gamma)
        prnu = None
        if op.prnu_sigma > 0:
            prnu = prnu_map(rng, (camera.height, camera.width), op.prnu_sigma)
        self.sensor = Sensor(
            response=response,
            gain=op.exposure_gain,
            shot_noise=op.shot_noise,
            full_well_e=op.full_well_e,
            read_noise_e=op.read_noise_e,
            prnu=prnu,
            bayer=op.bayer,
            demosaic=op.demosaic,
            noise_sigma=sc.camera.noise_sigma,
            noise_domain=op.noise_domain,
            vignetting=sc.camera.vignetting,
        )
        self.defocus: Defocus | None = None
        if op.defocus_px > 0:
            focus = standoff_m * (1.0 + op.focus_offset)
            k = op.defocus_px / max(abs(1.0 / standoff_m - 1.0 / focus), 1e-9)
            self.defocus = Defocus(k_px_m=k, focus_m=focus)
        self.vibration = Vibration(
            amplitude_m=op.vibration_m,
            amplitude_rad=op.vibration_rad,
            freq_hz=op.vibration_hz,
            damping_s=op.vibration_damping_s,
        )
        self.rng_noise = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2000, 1)))
        self.move_end_ns: float | None = None
        self.move_draw: tuple[F64, F64, float] | None = None

    # ------------------------------------------------------------------ streams
    def reseed(self, plan_index: int, faulted: bool) -> None:
        """The per-touch-up stream (sensor noise, vibration of its moves)."""
        ss = np.random.SeedSequence(self.seed, spawn_key=(2000, 1, plan_index, int(faulted)))
        self.rng_noise = np.random.default_rng(ss)

    def on_move(self, end_ns: float) -> None:
        """A commanded move ends at ``end_ns``: draw its after-move vibration."""
        self.move_end_ns = end_ns
        if self.vibration.active:
            self.move_draw = Vibration.draw(self.rng_noise)

    # ------------------------------------------------------------------ geometry
    def shaken(self, T_camera_target: F64, t_ns: float) -> F64:
        """``T_camera'_target`` with the vibration at ``t_ns`` (the encoders do not see it)."""
        if not self.vibration.active or self.move_draw is None or self.move_end_ns is None:
            return T_camera_target
        dt = (t_ns - self.move_end_ns) / 1e9
        V = self.vibration.transform(dt, self.move_draw)  # T_camera_camera'
        out: F64 = invert_transform(V) @ T_camera_target
        return out

    # ------------------------------------------------------------------ image
    @property
    def sensor_active(self) -> bool:
        return self.cfg.sensor_active()

    def form(self, irradiance: F64) -> tuple[np.ndarray, np.ndarray]:
        """Sensor and processing of :func:`pipeline.sim.optics.form_image`: (image, grey)."""
        return form_image(
            irradiance,
            self.sensor,
            principal_point=(self.camera.cx, self.camera.cy),
            rng_noise=self.rng_noise,
            rng_optics=self.rng_noise,
        )

    def encode(self, img: np.ndarray) -> tuple[str, bytes]:
        """Compressed bytes of ``img`` (JPEG with ``jpeg_quality``, else PNG): (format, data)."""
        if self.cfg.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.cfg.jpeg_quality])
            return "jpeg", buf.tobytes()
        ok, buf = cv2.imencode(".png", img)
        return "png", buf.tobytes()

    # ------------------------------------------------------------------ truth
    def truth(self) -> dict[str, Any]:
        """What the truth file records of the optics (every knob and every draw)."""
        s = self.sensor
        return {
            "config": asdict(self.cfg),
            "response": {
                "kind": s.response.kind,
                "gamma": s.response.gamma,
                "params": dict(s.response.params),
                "table": s.response.table(),
            },
            "defocus": None
            if self.defocus is None
            else {"k_px_m": self.defocus.k_px_m, "focus_m": self.defocus.focus_m},
            "prints": {str(k): v for k, v in self.prints.items()},
            "lights": {
                str(k): None
                if v is None
                else {
                    "gradient_per_m": list(v.gradient_per_m),
                    "sheen_grey": v.sheen_grey,
                    "sheen_width_rad": v.sheen_width_rad,
                }
                for k, v in self.lights.items()
            },
            "prnu_sigma": self.cfg.prnu_sigma,
        }
