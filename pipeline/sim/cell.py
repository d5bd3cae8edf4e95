"""The simulated world of one seed: true robot, camera and mount, targets, virtual pin.

:func:`build_cell` draws it from a scenario (deviations of the nominal URDF, a
camera with jittered intrinsics on a jittered flange mount, targets on tilted
plates); :func:`virtual_pin_camera` says where a perfect touch-up puts the
target; :func:`known_distances` and :func:`touchup_metadata` are what the
recording's ``touchup`` metadata record states of the cell (spec ``recording.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.kinematics.chain import Chain, load_chain
from pipeline.kinematics.se3 import F64, matrix_from_axis_angle, matrix_from_rpy, transform_from
from pipeline.kinematics.urdf import parse_urdf
from pipeline.measurement.image import depth_from_size, size_from_depth
from pipeline.robots import load_urdf
from pipeline.sim.camera import CameraModel
from pipeline.sim.robot import deviated_origins, draw_deviations, urdf_with_origins, urdf_with_pin
from pipeline.sim.scenario import Scenario
from pipeline.sim.target_geometry import projected_ellipse

#: Per built-in robot: home joint vector and the centre of the target area (base frame).
ROBOT_CELL: dict[str, dict[str, Any]] = {
    "lrmate": {"home": [0.0, 0.0, 0.0, 0.0, -1.5708, 0.0], "centre": [0.40, 0.0, 0.12]},
    "ur5e": {"home": [0.0, -0.8, 1.6, -2.37, -1.5708, 0.0], "centre": [0.45, 0.0, -0.05]},
    "iiwa7": {"home": [0.0, 0.5, 0.0, -1.4, 0.0, 1.2, 0.0], "centre": [0.55, 0.0, 0.15]},
}


@dataclass
class Target:
    id: int
    centre: F64
    normal: F64
    R: F64  # base <- target frame rotation (z = normal)
    history: list[dict[str, Any]] = field(default_factory=list)
    initial: F64 = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.initial = self.centre.copy()

    def T_base_target(self) -> F64:
        return transform_from(self.R, self.centre)


@dataclass
class Cell:
    robot_name: str
    nominal_urdf: str
    true_urdf: str
    true_urdf_with_pin: str
    nominal: Chain
    true: Chain
    deviations: dict[str, Any]
    camera: CameraModel
    T_flange_camera: F64
    p_vt_camera: F64
    p_vt_flange: F64
    u0: float
    v0: float
    s0: float
    targets: list[Target]
    home: F64


def rot_between(a: F64, b: F64) -> F64:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    v = np.cross(a, b)
    s = float(np.linalg.norm(v))
    c = float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return matrix_from_axis_angle(perp / np.linalg.norm(perp), np.pi)
    return matrix_from_axis_angle(v / s, np.arctan2(s, c))


def frame_from_normal(n: F64) -> F64:
    z = n / np.linalg.norm(n)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


#: Target frame in the camera frame for an untilted target: plate parallel to the
#: image plane, its normal ``+z`` pointing back at the camera (rotation pi about x).
R_CAMERA_UNTILTED = np.diag([1.0, -1.0, -1.0])


def virtual_pin_camera(
    camera: CameraModel, u0: float, v0: float, s0: float, diameter_m: float, iterations: int = 6
) -> F64:
    """Where a perfect touch-up puts the centre of an untilted target (camera frame).

    The spec (``spec/recording.md``) drives the ellipse fitted to the
    target contour to the designated centre ``(u0, v0)`` and long axis ``s0``.
    For a target whose plate is parallel to the image plane (no tilt: its
    perspective image is a circle) the pin is the circle centre ``p = (X, Y, Z)``
    solving

        E(p) = (u(p) - u0, v(p) - v0, s(p) - s0) = 0,

    with ``(u, v, s)`` the centre and long axis of
    :func:`pipeline.sim.target_geometry.projected_ellipse` (the circle's points through
    the full camera model). Without distortion this is ``Z = fx D / s0`` on the
    ray of ``(u0, v0)`` (:func:`pipeline.measurement.image.depth_from_size`). With radial distortion the disc's rim lies at
    normalised radius ``r = D / (2 Z)`` about its centre, and barrel distortion
    (``k1 < 0``) shrinks the image of the disc by ``1 + k1 r^2 + ...`` even at the
    principal point (``-6e-5`` for ``k1 = -0.07``, ``r = 0.03``): a perfect
    touch-up stops about ``Z k1 r^2`` (about 10 um) nearer the camera than
    ``fx D / s0``. Solved by Newton's method, starting from the pinhole answer,
    with a forward-difference Jacobian (``E`` is smooth and nearly linear).

    Parameters
    ----------
    camera : CameraModel
    u0, v0 : float
        Designated centre (px).
    s0 : float
        Designated long axis (px).
    diameter_m : float
        Target diameter ``D``.

    Returns
    -------
    (3,) ``p_vt_camera`` (m).
    """
    xu, yu = camera.pixel_to_normalised(np.array([u0, v0]))
    p = depth_from_size(camera.fx, diameter_m, s0) * np.array([xu, yu, 1.0])
    goal = np.array([u0, v0, s0])

    def err(pt: F64) -> F64:
        e = projected_ellipse(camera, transform_from(R_CAMERA_UNTILTED, pt), diameter_m)
        return np.array([e[0], e[1], e[2]]) - goal

    h = 1e-6
    for _ in range(iterations):
        e0 = err(p)
        if np.max(np.abs(e0)) < 1e-9:
            break
        J = np.stack([(err(p + h * np.eye(3)[k]) - e0) / h for k in range(3)], axis=1)
        p = p - np.linalg.solve(J, e0)
    return p


def build_cell(sc: Scenario, rng: np.random.Generator) -> Cell:
    """Draw the true world of one seed: deviations, camera, mount, targets."""
    base_dir = Path(sc.base_dir)
    name = sc.robot.urdf if sc.robot.urdf else sc.robot.name
    nominal_urdf = load_urdf(name, base_dir)
    nominal = load_chain(nominal_urdf, sc.robot.base_link, sc.robot.flange_link)
    deviations = draw_deviations(
        nominal, rng, sc.robot.sigma_xyz_m, sc.robot.sigma_rpy_rad, sc.robot.sigma_q0_rad
    )
    r = sc.robot
    if r.change_joint:  # an event on top of the drawn robot (the audit's image histories)
        if r.change_joint not in deviations:
            raise ValueError(f"[robot] change_joint {r.change_joint!r}: not an actuated joint")
        dev = deviations[r.change_joint]
        dev["dq0_rad"] = float(dev["dq0_rad"]) + float(r.change_dq0_rad)
        dev["dxyz_m"] = [
            float(a) + float(b) for a, b in zip(dev["dxyz_m"], r.change_dxyz_m, strict=True)
        ]
    origins = deviated_origins(nominal, deviations)
    true_urdf = urdf_with_origins(nominal_urdf, origins, name_suffix="_true")
    true = load_chain(true_urdf, sc.robot.base_link, sc.robot.flange_link)

    c = sc.camera
    f = c.f_px * (1.0 + rng.uniform(-c.f_jitter, c.f_jitter))
    camera = CameraModel(
        fx=f,
        fy=f,
        cx=(c.width - 1) / 2 + rng.normal(0.0, c.pp_jitter_px),
        cy=(c.height - 1) / 2 + rng.normal(0.0, c.pp_jitter_px),
        k1=c.k1 * (1.0 + rng.uniform(-0.2, 0.2)),
        k2=c.k2 * (1.0 + rng.uniform(-0.2, 0.2)),
        width=c.width,
        height=c.height,
    )
    tilt = rng.normal(0.0, c.mount_tilt_rad, 3)
    R_fc = matrix_from_rpy([0.0, 0.0, np.pi / 2]) @ matrix_from_rpy(tilt)
    p_fc = np.asarray(c.mount_xyz_m, dtype=float) + rng.uniform(
        -c.mount_jitter_m, c.mount_jitter_m, 3
    )
    T_flange_camera = transform_from(R_fc, p_fc)

    t = sc.touchup
    u0 = t.designated_u if t.designated_u is not None else (c.width - 1) / 2
    v0 = t.designated_v if t.designated_v is not None else (c.height - 1) / 2
    D = sc.targets.diameter_m
    s0 = round(size_from_depth(camera.fx, D, c.standoff_m), 3)
    p_vt_camera = virtual_pin_camera(camera, float(u0), float(v0), s0, D)
    p_vt_flange = R_fc @ p_vt_camera + p_fc

    cell_defaults = ROBOT_CELL.get(sc.robot.name, ROBOT_CELL["lrmate"])
    home = np.asarray(
        sc.robot.home if sc.robot.home is not None else cell_defaults["home"], dtype=float
    )
    if home.size != nominal.n_dof:
        home = np.clip(np.zeros(nominal.n_dof), nominal.lower, nominal.upper)
    centre = np.asarray(
        sc.targets.centre_m if sc.targets.centre_m is not None else cell_defaults["centre"],
        dtype=float,
    )
    n = sc.targets.count
    targets = []
    for i in range(n):
        y = 0.0 if n == 1 else -0.5 * sc.targets.spread_m + i * sc.targets.spread_m / (n - 1)
        pos = centre + np.array([0.0, y, 0.0]) + rng.uniform(-0.02, 0.02, 3)
        radial = np.array([pos[0], pos[1], 0.0])
        radial /= max(np.linalg.norm(radial), 1e-9)
        tilt_rad = np.deg2rad(sc.targets.tilt_deg) * (1.0 + rng.uniform(-0.3, 0.3))
        normal = np.array([0.0, 0.0, 1.0]) * np.cos(tilt_rad) - radial * np.sin(tilt_rad)
        normal = matrix_from_axis_angle([0.0, 0.0, 1.0], rng.normal(0.0, 0.05)) @ normal
        R = frame_from_normal(normal)
        targets.append(Target(i, pos, R[:, 2].copy(), R))
    return Cell(
        robot_name=parse_urdf(nominal_urdf).name,
        nominal_urdf=nominal_urdf,
        true_urdf=true_urdf,
        true_urdf_with_pin=urdf_with_pin(true_urdf, sc.robot.flange_link, p_vt_flange),
        nominal=nominal,
        true=true,
        deviations=deviations,
        camera=camera,
        T_flange_camera=T_flange_camera,
        p_vt_camera=p_vt_camera,
        p_vt_flange=p_vt_flange,
        u0=float(u0),
        v0=float(v0),
        s0=float(s0),
        targets=targets,
        home=home,
    )


def known_distances(sc: Scenario, cell: Cell, labels: dict[int, int]) -> list[dict[str, Any]]:
    """The calibration bar (scenario ``[targets] bar``): the first and last target's distance.

    Labels are the order in which the run first touches the targets up (spec
    ``recording.md``, ``known_distances``); ``metres`` is rounded as the metadata
    states it, ``true_metres`` is not.
    """
    known: list[dict[str, Any]] = []
    if sc.targets.bar and len(cell.targets) >= 2:
        a, b = cell.targets[0], cell.targets[-1]
        if a.id in labels and b.id in labels:
            d = float(np.linalg.norm(a.centre - b.centre))
            la, lb = sorted((labels[a.id], labels[b.id]))
            ida, idb = (a.id, b.id) if labels[a.id] <= labels[b.id] else (b.id, a.id)
            known.append(
                {
                    "labels": [la, lb],
                    "target_ids": [ida, idb],
                    "metres": round(d, 6),
                    "true_metres": d,
                }
            )
    return known


def touchup_metadata(sc: Scenario, cell: Cell, known: list[dict[str, Any]]) -> dict[str, str]:
    """The recording's ``touchup`` metadata record (spec ``recording.md``) for this cell."""
    tt = sc.touchup
    metadata = {
        "base_link": sc.robot.base_link,
        "flange_link": sc.robot.flange_link,
        "target_diameter_m": f"{sc.targets.diameter_m:.3f}",
        "designated_u": f"{cell.u0:g}",
        "designated_v": f"{cell.v0:g}",
        "designated_size_px": f"{cell.s0:.3f}",
        "threshold_px": f"{tt.threshold_px:g}",
        "threshold_size_px": f"{tt.threshold_size_px:g}",
        "polarity": sc.targets.polarity,
    }
    if sc.robot.robot_id:
        metadata["robot_id"] = sc.robot.robot_id
    if known:
        metadata["known_distances"] = ";".join(
            f"{k['labels'][0]}:{k['labels'][1]}={k['metres']:.6f}" for k in known
        )
    return metadata
