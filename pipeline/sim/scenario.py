"""Simulation scenarios: TOML files in ``datasets/scenarios/`` read into typed settings.

Every key is optional; the defaults below make the standard cell (LR Mate-like
arm, 3 targets x 12 poses, 640 x 512 PNG images, a calibration bar). Sections
and keys (see ``docs/simulator.md`` for the meaning of each)::

    [robot]    name | urdf, base_link, flange_link, sigma_xyz_m, sigma_rpy_rad, sigma_q0_rad,
               robot_id (written as the recording's robot_id), cell_seed (draw the robot,
               camera and targets from this seed, the session from --seed: the same
               robot re-recorded; -1, the default, draws all from --seed), change_joint,
               change_dq0_rad, change_dxyz_m (that joint's zero and origin changed by
               these on top of the drawn robot: an event between two recordings)
    [camera]   width, height, f_px, f_jitter, pp_jitter_px, k1, k2, standoff_m,
               mount_xyz_m, mount_jitter_m, mount_tilt_rad, image ("png"|"raw"),
               blur_sigma_px, noise_sigma, vignetting, exposure_s, latency_s, subsamples
    [targets]  count, diameter_m, polarity, plate_radius_m, bar, centre_m, spread_m,
               tilt_deg, levels (target, plate, background)
    [touchup]  threshold_px, threshold_size_px, gain, max_iterations, repeat_captures,
               probe_shift_m, designated_u, designated_v, controller ("moments"|"binary")
    [poses]    per_target, cone_half_angle_deg, roll_range_deg, plan (Parquet path)
    [timing]   joint_rate_hz, encoder_noise_rad, start_ns, settle_s, compute_s,
               max_speed_rad_s, chunk_size
    [faults]   capture_while_moving, second_blob, unconverged, knocked_target,
               joint_state_gap, lost_target, truncate (booleans)
    [optics]   response ("linear"|"srgb"|"gamma"|"curve"), gamma, exposure_gain,
               shot_noise, full_well_e, read_noise_e, prnu_sigma, bayer, demosaic,
               jpeg_quality, defocus_px, focus_offset, illumination, sheen_grey,
               sheen_width_rad, out_of_round_um, roughness_um, diameter_scale_error,
               diameter_sigma_um, vibration_m, vibration_rad, vibration_hz,
               vibration_damping_s (real-camera image formation, all off by default)
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.errors import BadInput


@dataclass(frozen=True)
class RobotCfg:
    name: str = "lrmate"
    urdf: str | None = None
    base_link: str = "base_link"
    flange_link: str = "flange"
    sigma_xyz_m: float = 5e-4
    sigma_rpy_rad: float = 1.5e-3
    sigma_q0_rad: float = 1e-3
    home: tuple[float, ...] | None = None
    robot_id: str = ""
    cell_seed: int = -1
    change_joint: str = ""
    change_dq0_rad: float = 0.0
    change_dxyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CameraCfg:
    width: int = 640
    height: int = 512
    f_px: float = 900.0
    f_jitter: float = 0.03
    pp_jitter_px: float = 4.0
    k1: float = -0.07
    k2: float = 0.007
    standoff_m: float = 0.17
    mount_xyz_m: tuple[float, float, float] = (0.03, 0.0, 0.08)
    mount_jitter_m: float = 0.005
    mount_tilt_rad: float = 0.05
    image: str = "png"
    blur_sigma_px: float = 0.7
    noise_sigma: float = 2.0
    vignetting: float = 0.15
    exposure_s: float = 0.01
    latency_s: float = 0.03
    subsamples: int = 16


@dataclass(frozen=True)
class TargetsCfg:
    count: int = 3
    diameter_m: float = 0.010
    polarity: str = "dark_on_light"
    plate_radius_m: float = 0.03
    bar: bool = True
    centre_m: tuple[float, float, float] | None = None
    spread_m: float = 0.6
    tilt_deg: float = 15.0
    levels: tuple[float, float, float] = (40.0, 200.0, 170.0)


@dataclass(frozen=True)
class TouchupCfg:
    threshold_px: float = 0.5
    threshold_size_px: float = 0.5
    gain: float = 0.9
    max_iterations: int = 12
    repeat_captures: int = 3
    probe_shift_m: float = 0.002
    designated_u: float | None = None
    designated_v: float | None = None
    controller: str = "moments"


@dataclass(frozen=True)
class PosesCfg:
    per_target: int = 12
    cone_half_angle_deg: float = 30.0
    roll_range_deg: float = 60.0
    plan: str | None = None


@dataclass(frozen=True)
class TimingCfg:
    joint_rate_hz: float = 100.0
    encoder_noise_rad: float = 1e-6
    start_ns: int = 1_700_000_000_000_000_000
    settle_s: float = 0.15
    compute_s: float = 0.2
    max_speed_rad_s: float = 1.0
    chunk_size: int = 4 * 1024 * 1024


@dataclass(frozen=True)
class FaultsCfg:
    capture_while_moving: bool = False
    second_blob: bool = False
    unconverged: bool = False
    knocked_target: bool = False
    joint_state_gap: bool = False
    lost_target: bool = False
    truncate: bool = False

    def any(self) -> bool:
        return any(dataclasses.asdict(self).values())


@dataclass(frozen=True)
class OpticsCfg:
    """Real-camera image formation (:mod:`pipeline.sim.optics`); the defaults are all off.

    response, gamma : the camera's response curve (``curve``: an unknown monotone curve
        drawn from the seed); exposure_gain : linear grey 255 -> this fraction of the full
        well (above 1 saturates the plate); shot_noise, full_well_e, read_noise_e,
        prnu_sigma : sensor noise; bayer, demosaic : RGGB mosaic, demosaiced to BGR (the
        recording then carries ``bgr8`` / colour PNG / JPEG); jpeg_quality : 1..100 writes
        JPEG CompressedImage instead of PNG/raw (0: off); defocus_px, focus_offset : thin-lens
        pillbox of radius ``defocus_px`` at the stand-off, focus at ``(1 + focus_offset)``
        times the stand-off; illumination : fraction of irradiance change across the plate
        (direction drawn per target); sheen_grey, sheen_width_rad : specular lobe of a ring
        light; out_of_round_um, roughness_um, diameter_scale_error, diameter_sigma_um : the
        printed targets (:func:`pipeline.sim.optics.draw_print`); vibration_* : damped
        oscillation of the camera after each move (:class:`pipeline.sim.optics.Vibration`);
        noise_domain : where ``[camera] noise_sigma`` enters when the response is not
        linear: ``sensor`` (before the curve, as a real sensor's read and shot noise do;
        the default) or ``output`` (added to the encoded grey levels, vtcal's simulator's
        earlier default). A linear response gives the same image either way.
    """

    response: str = "linear"
    gamma: float = 2.2
    exposure_gain: float = 1.0
    shot_noise: bool = False
    full_well_e: float = 10000.0
    read_noise_e: float = 0.0
    prnu_sigma: float = 0.0
    bayer: bool = False
    demosaic: str = "bilinear"
    jpeg_quality: int = 0
    defocus_px: float = 0.0
    focus_offset: float = -0.1
    illumination: float = 0.0
    sheen_grey: float = 0.0
    sheen_width_rad: float = 0.26
    out_of_round_um: float = 0.0
    roughness_um: float = 0.0
    diameter_scale_error: float = 0.0
    diameter_sigma_um: float = 0.0
    vibration_m: float = 0.0
    vibration_rad: float = 0.0
    vibration_hz: float = 15.0
    vibration_damping_s: float = 0.3
    noise_domain: str = "sensor"

    def sensor_active(self) -> bool:
        """Whether the image is formed by :func:`pipeline.sim.optics.form_image`."""
        return (
            self.response != "linear"
            or self.exposure_gain != 1.0
            or self.shot_noise
            or self.read_noise_e > 0
            or self.prnu_sigma > 0
            or self.bayer
        )

    def print_active(self) -> bool:
        return (
            self.out_of_round_um > 0
            or self.roughness_um > 0
            or self.diameter_scale_error != 0
            or self.diameter_sigma_um > 0
        )

    def any(self) -> bool:
        return self != OpticsCfg()


@dataclass(frozen=True)
class Scenario:
    name: str = "standard"
    robot: RobotCfg = field(default_factory=RobotCfg)
    camera: CameraCfg = field(default_factory=CameraCfg)
    targets: TargetsCfg = field(default_factory=TargetsCfg)
    touchup: TouchupCfg = field(default_factory=TouchupCfg)
    poses: PosesCfg = field(default_factory=PosesCfg)
    timing: TimingCfg = field(default_factory=TimingCfg)
    faults: FaultsCfg = field(default_factory=FaultsCfg)
    optics: OpticsCfg = field(default_factory=OpticsCfg)
    base_dir: str = "."

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("base_dir")
        return d


_SECTIONS: dict[str, type] = {
    "robot": RobotCfg,
    "camera": CameraCfg,
    "targets": TargetsCfg,
    "touchup": TouchupCfg,
    "poses": PosesCfg,
    "timing": TimingCfg,
    "faults": FaultsCfg,
    "optics": OpticsCfg,
}


def _section(cls: type, raw: Any, where: str) -> Any:
    if not isinstance(raw, dict):
        raise BadInput(f"{where}: must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kw: dict[str, Any] = {}
    for k, v in raw.items():
        if k not in fields:
            raise BadInput(f"{where}: unknown key {k!r} (known: {', '.join(fields)})")
        default = fields[k].default
        if isinstance(v, list):
            v = tuple(v)
        if isinstance(default, bool) and not isinstance(v, bool):
            raise BadInput(f"{where}.{k}: {v!r} is not true/false")
        if isinstance(default, float) and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if isinstance(default, (int, float, str)) and not isinstance(v, type(default)):
            raise BadInput(f"{where}.{k}: {v!r} is not a {type(default).__name__}")
        kw[k] = v
    return cls(**kw)


def scenario_from_dict(
    raw: dict[str, Any], where: str = "scenario", base_dir: str = "."
) -> Scenario:
    """Build a :class:`Scenario` from a parsed TOML table (unknown keys are errors)."""
    kw: dict[str, Any] = {"base_dir": base_dir}
    for k, v in raw.items():
        if k == "name":
            kw["name"] = str(v)
        elif k in _SECTIONS:
            kw[k] = _section(_SECTIONS[k], v, f"{where} [{k}]")
        else:
            raise BadInput(f"{where}: unknown section {k!r} (known: name, {', '.join(_SECTIONS)})")
    sc = Scenario(**kw)
    if sc.targets.polarity not in ("dark_on_light", "light_on_dark"):
        raise BadInput(
            f"{where} [targets] polarity {sc.targets.polarity!r} is not dark_on_light/light_on_dark"
        )
    if sc.camera.image not in ("png", "raw"):
        raise BadInput(f"{where} [camera] image {sc.camera.image!r} is not 'png' or 'raw'")
    if sc.touchup.controller not in ("moments", "binary"):
        raise BadInput(
            f"{where} [touchup] controller {sc.touchup.controller!r} is not moments/binary"
        )
    op = sc.optics
    if op.response not in ("linear", "srgb", "gamma", "curve"):
        raise BadInput(f"{where} [optics] response {op.response!r} is not linear/srgb/gamma/curve")
    if op.noise_domain not in ("sensor", "output"):
        raise BadInput(f"{where} [optics] noise_domain {op.noise_domain!r} is not sensor/output")
    if op.demosaic not in ("bilinear", "ea", "vng"):
        raise BadInput(f"{where} [optics] demosaic {op.demosaic!r} is not bilinear/ea/vng")
    if not 0 <= op.jpeg_quality <= 100:
        raise BadInput(f"{where} [optics] jpeg_quality {op.jpeg_quality} is not 0..100")
    if op.exposure_gain <= 0 or op.gamma <= 0 or op.full_well_e <= 0:
        raise BadInput(f"{where} [optics] exposure_gain, gamma and full_well_e must be > 0")
    if sc.targets.count < 1 or sc.poses.per_target < 1:
        raise BadInput(f"{where}: needs at least one target and one pose per target")
    return sc


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario TOML file.

    Raises
    ------
    BadInput
        Missing file, bad TOML, unknown section/key or a value of the wrong type.
    """
    p = Path(path)
    if not p.exists():
        raise BadInput(f"{p}: scenario file not found")
    try:
        raw = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise BadInput(f"{p}: not valid TOML: {exc}") from exc
    raw.setdefault("name", p.stem)
    return scenario_from_dict(raw, where=str(p), base_dir=str(p.parent))
