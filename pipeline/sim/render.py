"""Accurate rendering of a circular target on a plate by area coverage.

The scene seen by one capture is a plane (the plate, target frame ``z = 0``,
normal ``+z`` towards the camera) carrying nested discs: the plate
(``plate_radius_m``, grey ``plate``), optional extra discs (a second blob) and
the target (diameter ``D``, grey ``target``) at the origin; outside the plate
the background grey. Rendering is by area coverage:

1. every pixel centre is back-projected through the camera (exact inverse of
   the radial distortion) and intersected with the plane, giving its plane
   coordinates ``(x, y)``;
2. a pixel whose centre lies farther from a disc edge than its own footprint
   is wholly inside or outside that disc; every other (edge) pixel is
   supersampled on an ``N x N`` grid of sub-pixel points, each back-projected
   exactly (so distortion and perspective are exact inside the pixel), and
   its coverage is the fraction of sub-points inside the disc;
3. layers are composited back to front, ``g <- g (1 - c) + g_layer c``;
4. then Gaussian blur (optics; around the target evaluated on a finer grid
   before pixel integration, see :func:`render_ideal`) and the sensor
   (:mod:`pipeline.sim.image_finish`: vignetting, exposure, noise, ``uint8``).

A capture during motion averages step 1-3 over several poses of the exposure
(``T_camera_target`` of shape ``(K, 4, 4)``).

Real-camera effects (:mod:`pipeline.sim.optics`, scenario ``[optics]``) enter
here where they act on the scene: a printed target that is not a perfect circle
(:class:`~pipeline.sim.target_geometry.PrintShape`, boundary radius as a function
of the polar angle in the plate frame, used by every inside test), the
illumination of the plate (:class:`~pipeline.sim.optics.PlateLight`, evaluated
per point of the plate before the blur) and thin-lens defocus
(:class:`~pipeline.sim.optics.Defocus`, a pillbox whose radius follows the plate
depth, after the Gaussian blur). Without them (the defaults) the code paths are
those of a perfect circle, uniformly lit, in focus.

The reference geometry, the exactly projected ellipse the rendered disc is
judged against, is :mod:`pipeline.sim.target_geometry`.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64
from pipeline.sim.camera import CameraModel
from pipeline.sim.image_finish import Occluder, finish_image
from pipeline.sim.optics import Defocus, PlateLight, variable_pillbox
from pipeline.sim.target_geometry import PrintShape

#: (x_m, y_m, diameter_m, grey) of an extra disc in the target plane.
ExtraDisc = tuple[float, float, float, float]


#: A disc layer's boundary: a radius (m, perfect circle) or a printed shape.
Boundary = float | PrintShape
#: A disc layer: centre ``(x, y)`` in the plate frame (m), boundary, grey.
Layer = tuple[tuple[float, float], Boundary, float]


def _boundary(shape: PrintShape | None, diameter_m: float) -> Boundary:
    """The target layer's boundary: a plain radius unless the print is not a circle."""
    if shape is None:
        return 0.5 * diameter_m
    if shape.is_circle:
        return shape.radius_m
    return shape


def _max_radius(b: Boundary) -> float:
    return b.max_radius() if isinstance(b, PrintShape) else float(b)


def _plane_coords(
    camera: CameraModel, T_camera_target: F64, xy_norm: F64
) -> tuple[F64, np.ndarray]:
    """Intersect rays ``(x, y, 1)`` with the target plane.

    Returns plane coordinates ``(..., 2)`` in the target frame and a mask of
    rays that hit the plane in front of the camera.
    """
    R = T_camera_target[:3, :3]
    t = T_camera_target[:3, 3]
    n = R[:, 2]
    denom = xy_norm[..., 0] * n[0] + xy_norm[..., 1] * n[1] + n[2]
    num = float(n @ t)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num / denom
    ok = np.isfinite(s) & (s > 0)
    s = np.where(ok, s, 0.0)
    # p_target = R^T (s d - t)
    px = s * xy_norm[..., 0] - t[0]
    py = s * xy_norm[..., 1] - t[1]
    pz = s - t[2]
    x = R[0, 0] * px + R[1, 0] * py + R[2, 0] * pz
    y = R[0, 1] * px + R[1, 1] * py + R[2, 1] * pz
    out = np.stack([x, y], axis=-1)
    out[~ok] = 1e9
    return out, ok


def _roi(camera: CameraModel, T_camera_target: F64, radius: float) -> tuple[int, int, int, int]:
    """Pixel bounding box ``(u0, u1, v0, v1)`` (exclusive ends) of a disc, or the image."""
    W, H = camera.width, camera.height
    a = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
    pts = np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros_like(a)], axis=-1)
    p_cam = pts @ T_camera_target[:3, :3].T + T_camera_target[:3, 3]
    if np.any(p_cam[:, 2] <= 1e-6):
        return 0, W, 0, H
    uv = camera.project(p_cam)
    if not np.all(np.isfinite(uv)):
        return 0, W, 0, H
    # distortion can fold far-off points back; be generous with the margin
    m = 4
    u0 = int(np.clip(np.floor(uv[:, 0].min()) - m, 0, W))
    u1 = int(np.clip(np.ceil(uv[:, 0].max()) + m + 1, 0, W))
    v0 = int(np.clip(np.floor(uv[:, 1].min()) - m, 0, H))
    v1 = int(np.clip(np.ceil(uv[:, 1].max()) + m + 1, 0, H))
    return u0, u1, v0, v1


def _footprint(xy: F64, ok: np.ndarray, floor: float) -> F64:
    """Conservative footprint (m) of each grid cell on the plane, ``(h, w)``.

    ``0.75 (|d xy / du| + |d xy / dv|) + floor`` where the ray hits the plane, 0
    elsewhere, capped at 1 m: a cell whose centre is farther than this from a disc
    edge is wholly inside or outside that disc.
    """
    gu = np.linalg.norm(np.gradient(xy, axis=1), axis=-1)
    gv = np.linalg.norm(np.gradient(xy, axis=0), axis=-1)
    foot: F64 = np.minimum(np.where(ok, 0.75 * (gu + gv) + floor, 0.0), 1.0)
    return foot


def _subsample_plane(
    camera: CameraModel, T_camera_target: F64, centres: F64, subsamples: int, cell: float
) -> tuple[F64, np.ndarray]:
    """Plate coordinates of an ``n x n`` grid of points in each ``cell``-px square.

    ``centres`` (M, 2) pixel centres; returns ``(M, n*n, 2)`` plate ``(x, y)`` and
    ``(M, n*n)`` whether each ray meets the plate in front of the camera.
    """
    n = max(int(subsamples), 1)
    off = cell * ((np.arange(n) + 0.5) / n - 0.5)
    ou, ov = np.meshgrid(off, off)
    sub = np.stack([ou.ravel(), ov.ravel()], axis=-1)  # (n*n, 2)
    pts = centres[:, None, :] + sub[None, :, :]  # (M, n*n, 2)
    return _plane_coords(camera, T_camera_target, camera.pixel_to_normalised(pts))


def _coverage(
    camera: CameraModel,
    T_camera_target: F64,
    xy: F64,
    ok: np.ndarray,
    foot: F64,
    uv_grid: F64,
    centre: tuple[float, float],
    radius: Boundary,
    subsamples: int,
    cell: float = 1.0,
) -> F64:
    """Area fraction of each ROI cell (a pixel, or a ``cell``-px square) inside one disc.

    ``radius`` is a circle's radius, or a :class:`PrintShape` whose boundary
    ``r(phi)`` (polar angle about ``centre`` in the plate frame) every inside
    test then uses.
    """
    if isinstance(radius, PrintShape):
        return _coverage_shape(
            camera, T_camera_target, xy, ok, foot, uv_grid, centre, radius, subsamples, cell
        )
    rho = np.hypot(xy[..., 0] - centre[0], xy[..., 1] - centre[1])
    cov = ((rho <= radius) & ok).astype(float)
    band = np.abs(rho - radius) <= foot
    if not np.any(band):
        return cov
    sxy, sok = _subsample_plane(camera, T_camera_target, uv_grid[band], subsamples, cell)
    inside = (np.hypot(sxy[..., 0] - centre[0], sxy[..., 1] - centre[1]) <= radius) & sok
    cov[band] = inside.mean(axis=1)
    return cov


def _coverage_shape(
    camera: CameraModel,
    T_camera_target: F64,
    xy: F64,
    ok: np.ndarray,
    foot: F64,
    uv_grid: F64,
    centre: tuple[float, float],
    shape: PrintShape,
    subsamples: int,
    cell: float,
) -> F64:
    """:func:`_coverage` for a non-circular printed boundary ``r(phi)``."""
    dx = xy[..., 0] - centre[0]
    dy = xy[..., 1] - centre[1]
    rho = np.hypot(dx, dy)
    rb = shape.radius_at(np.arctan2(dy, dx))
    cov = ((rho <= rb) & ok).astype(float)
    band = np.abs(rho - rb) <= foot * shape.band_factor()
    if not np.any(band):
        return cov
    sxy, sok = _subsample_plane(camera, T_camera_target, uv_grid[band], subsamples, cell)
    sdx = sxy[..., 0] - centre[0]
    sdy = sxy[..., 1] - centre[1]
    inside = (np.hypot(sdx, sdy) <= shape.radius_at(np.arctan2(sdy, sdx))) & sok
    cov[band] = inside.mean(axis=1)
    return cov


def _grey_field(
    light: PlateLight | None, grey: float, xy: F64, ok: np.ndarray, T: F64
) -> float | F64:
    """A layer's radiance: its grey, or (with ``light``) the lit field on the plate."""
    if light is None:
        return grey
    return light.radiance(grey, xy, ok, T)


def _plane_depth(T_camera_target: F64, rays: F64) -> F64:
    """Depth ``z`` (m) where rays ``(x, y, 1)`` ``(..., 2)`` meet the plate plane; 0 if never."""
    R = T_camera_target[:3, :3]
    t = T_camera_target[:3, 3]
    n = R[:, 2]
    denom = rays[..., 0] * n[0] + rays[..., 1] * n[1] + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = float(n @ t) / denom
    out: F64 = np.where(np.isfinite(s) & (s > 0), s, 0.0)
    return out


def render_ideal(
    camera: CameraModel,
    T_camera_target: ArrayLike,
    diameter_m: float,
    *,
    levels: tuple[float, float] = (40.0, 200.0),
    plate_radius_m: float = 0.03,
    background_grey: float | None = None,
    extra_discs: Sequence[ExtraDisc] = (),
    subsamples: int = 16,
    blur_sigma_px: float = 0.0,
    fine: int = 4,
    target_shape: PrintShape | None = None,
    light: PlateLight | None = None,
    defocus: Defocus | None = None,
) -> F64:
    """Noise-free grey image ``(H, W)`` float by area coverage (steps 1-3), optionally blurred.

    ``T_camera_target`` may be ``(K, 4, 4)``: the mean over the K poses (motion
    during the exposure).

    With ``blur_sigma_px > 0`` the optical blur is applied here, in the order the
    physics has it: the scene is blurred first and each pixel then integrates the
    blurred irradiance over its area, ``g = box * (G_sigma * scene)``. Around the
    target this is computed on a ``fine x fine`` grid per pixel (area coverage of
    each fine cell, Gaussian blur of ``sigma * fine`` fine cells, then the mean
    over each pixel's cells), because blurring already pixel-integrated values
    with a discrete ``sigma = 0.7 px`` kernel aliases: the blurred edge profile
    would then shift with the target's sub-pixel position (a few thousandths of
    a pixel of size, tens of micrometres of pin depth). Elsewhere (plate edge,
    background) the discrete blur of pixel values is used.

    Optional real-camera effects (``None``: off, the code paths of before):

    target_shape : PrintShape
        The printed target's boundary (else a circle of ``diameter_m``).
    light : PlateLight
        Illumination gradient and sheen on the plate and what is printed on it
        (the background outside the plate stays ``background_grey``).
    defocus : Defocus
        Pillbox blur of radius ``defocus.radius_px(z)`` at the plate depth ``z``
        of every pixel (of every fine cell around the target), after the
        Gaussian blur (:func:`pipeline.sim.optics.variable_pillbox`).
    """
    T_all = np.asarray(T_camera_target, dtype=float)
    if T_all.ndim == 2:
        T_all = T_all[None]
    target_grey, plate_grey = float(levels[0]), float(levels[1])
    bg = 0.85 * plate_grey if background_grey is None else float(background_grey)
    H, W = camera.height, camera.width
    acc = np.zeros((H, W))
    rays_all = camera.pixel_rays()
    target_b = _boundary(target_shape, diameter_m)
    layers = _layers(plate_radius_m, plate_grey, extra_discs, target_b, target_grey)
    for T in T_all:
        img = _render_pose(camera, T, rays_all, plate_radius_m, layers, bg, subsamples, light)
        if defocus is not None:
            img = variable_pillbox(img, defocus.radius_px(_plane_depth(T, rays_all)))
        acc += img
    acc /= len(T_all)
    if blur_sigma_px <= 0:
        return acc
    blurred = cv2.GaussianBlur(acc, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    box = _target_box(camera, T_all, target_b, plate_radius_m, blur_sigma_px, defocus)
    if box is not None:
        u0, u1, v0, v1 = box
        region = np.zeros((v1 - v0, u1 - u0))
        for T in T_all:
            region += _fine_blurred_region(
                camera,
                T,
                box,
                layers,
                bg,
                blur_sigma_px,
                fine,
                subsamples,
                light=light,
                defocus=defocus,
            )
        blurred[v0:v1, u0:u1] = region / len(T_all)
    result: F64 = np.asarray(blurred, dtype=float)
    return result


def _layers(
    plate_radius_m: float,
    plate_grey: float,
    extra_discs: Sequence[ExtraDisc],
    target: Boundary,
    target_grey: float,
) -> list[Layer]:
    """The scene's discs back to front: the plate, the extra discs, the target."""
    layers: list[Layer] = [((0.0, 0.0), plate_radius_m, plate_grey)]
    layers += [((float(x), float(y)), 0.5 * float(d), float(g)) for x, y, d, g in extra_discs]
    layers.append(((0.0, 0.0), target, target_grey))
    return layers


def _render_pose(
    camera: CameraModel,
    T: F64,
    rays_all: F64,
    plate_radius_m: float,
    layers: Sequence[Layer],
    bg: float,
    subsamples: int,
    light: PlateLight | None,
) -> F64:
    """Steps 1-3 at one pose ``T`` (4, 4): the ``(H, W)`` image, the plate's box by area
    coverage (the plate edge, ``layers[0]``, supersampled 4 x 4; every other disc edge
    ``subsamples x subsamples``), the background ``bg`` elsewhere."""
    img = np.full((camera.height, camera.width), bg)
    u0, u1, v0, v1 = _roi(camera, T, plate_radius_m)
    if u1 > u0 and v1 > v0:
        rays = rays_all[v0:v1, u0:u1]
        vv, uu = np.mgrid[v0:v1, u0:u1].astype(float)
        uv_grid = np.stack([uu, vv], axis=-1)
        xy, ok = _plane_coords(camera, T, rays)
        if xy.shape[0] > 1 and xy.shape[1] > 1:
            foot = _footprint(xy, ok, 1e-9)
        else:
            foot = np.full(xy.shape[:2], 1.0)
        roi = np.full(xy.shape[:2], bg)
        for j, (c, r, g) in enumerate(layers):
            ns = 4 if j == 0 else subsamples
            cov = _coverage(camera, T, xy, ok, foot, uv_grid, c, r, ns)
            roi = roi * (1.0 - cov) + _grey_field(light, g, xy, ok, T) * cov
        img[v0:v1, u0:u1] = roi
    return img


def _target_box(
    camera: CameraModel,
    T_all: F64,
    target: Boundary,
    plate_radius_m: float,
    blur_sigma_px: float,
    defocus: Defocus | None,
) -> tuple[int, int, int, int] | None:
    """Pixel box ``(u0, u1, v0, v1)`` of the target over the poses ``T_all`` (K, 4, 4), with a
    margin for the Gaussian blur (and the largest defocus pillbox over the plate): where
    :func:`render_ideal` blurs on the fine grid. None if it is empty or spans the image."""
    W, H = camera.width, camera.height
    margin = int(np.ceil(4.0 * blur_sigma_px)) + 3
    if defocus is not None:
        depths = [float(T[2, 3]) + s * plate_radius_m for T in T_all for s in (-1.0, 1.0)]
        margin += int(np.ceil(float(np.max(defocus.radius_px(np.array(depths))))))
    boxes = [_roi(camera, T, _max_radius(target)) for T in T_all]
    u0 = max(min(b[0] for b in boxes) - margin, 0)
    u1 = min(max(b[1] for b in boxes) + margin, W)
    v0 = max(min(b[2] for b in boxes) - margin, 0)
    v1 = min(max(b[3] for b in boxes) + margin, H)
    if u1 - u0 < W and v1 - v0 < H and u1 > u0 and v1 > v0:
        return u0, u1, v0, v1
    return None


def _fine_blurred_region(
    camera: CameraModel,
    T: F64,
    box: tuple[int, int, int, int],
    layers: Sequence[Layer],
    bg: float,
    sigma_px: float,
    fine: int,
    subsamples: int,
    *,
    light: PlateLight | None = None,
    defocus: Defocus | None = None,
) -> F64:
    """Pixels of ``box`` as ``box * (G_sigma * scene)``, evaluated on a ``fine``-times grid.

    Each fine cell gets its area coverage of every disc (``subsamples / fine``
    points per side in edge cells, at least 4), the fine image is blurred with
    ``sigma_px * fine`` cells (replicated borders: the box has a margin of
    uniform plate around the target) and averaged back to pixels. With
    ``light`` the layers' greys are the lit radiance at each fine cell; with
    ``defocus`` the fine image is then blurred by the depth-dependent pillbox
    (radius ``fine * r_px(z)`` cells, ``z`` the plate depth of each cell).
    """
    u0, u1, v0, v1 = box
    k = max(int(fine), 1)
    off = (np.arange(k) + 0.5) / k - 0.5
    us = (np.arange(u0, u1)[:, None] + off[None, :]).ravel()
    vs = (np.arange(v0, v1)[:, None] + off[None, :]).ravel()
    uu, vv = np.meshgrid(us, vs)
    uv = np.stack([uu, vv], axis=-1)
    xy, ok = _plane_coords(camera, T, camera.pixel_to_normalised(uv))
    foot = _footprint(xy, ok, 1e-12)
    img = np.full(xy.shape[:2], bg)
    n_sub = max(4, int(np.ceil(subsamples / k)))
    for c, r, g in layers:
        cov = _coverage(camera, T, xy, ok, foot, uv, c, r, n_sub, cell=1.0 / k)
        img = img * (1.0 - cov) + _grey_field(light, g, xy, ok, T) * cov
    img = cv2.GaussianBlur(img, (0, 0), sigma_px * k, borderType=cv2.BORDER_REPLICATE)
    if defocus is not None:
        z = T[2, 0] * xy[..., 0] + T[2, 1] * xy[..., 1] + T[2, 3]
        z = np.where(ok, z, 0.0)
        img = variable_pillbox(
            np.asarray(img, dtype=float), k * defocus.radius_px(z), step=0.25 * k
        )
    h, w = v1 - v0, u1 - u0
    out: F64 = img.reshape(h, k, w, k).mean(axis=(1, 3))
    return out


def render_target_image(
    camera: CameraModel,
    T_camera_target: ArrayLike,
    diameter_m: float,
    *,
    levels: tuple[float, float] = (40.0, 200.0),
    plate_radius_m: float = 0.03,
    blur_sigma_px: float = 0.7,
    noise_sigma: float = 2.0,
    vignetting: float = 0.15,
    rng: np.random.Generator | None = None,
    extra_discs: Sequence[ExtraDisc] = (),
    background_grey: float | None = None,
    exposure: float = 1.0,
    occluders: Sequence[Occluder] = (),
    subsamples: int = 16,
) -> np.ndarray:
    """Render one camera image of a circular target on its plate.

    Parameters
    ----------
    camera : CameraModel
    T_camera_target : (4, 4) or (K, 4, 4)
        Target frame in the camera frame: circle centre at the origin, plate
        normal ``+z`` (towards the camera for a visible target). ``(K, 4, 4)``
        averages K poses over the exposure (motion blur).
    diameter_m : float
        Target circle diameter ``D``.
    levels : (target_grey, plate_grey)
        Grey levels before vignetting/exposure; ``(40, 200)`` is dark on
        light, ``(200, 40)`` light on dark.
    plate_radius_m : float
        Radius of the circular plate carrying the target.
    blur_sigma_px, noise_sigma, vignetting, exposure : float
        Optics and sensor (see :func:`finish_image`).
    rng : numpy Generator, optional
        Source of the sensor noise (default: a fixed seed).
    extra_discs : sequence of (x_m, y_m, diameter_m, grey)
        Further discs painted on the plate (e.g. a second blob).
    background_grey : float, optional
        Grey outside the plate (default ``0.85 * plate_grey``).
    occluders : sequence of (u, v, a_px, b_px, angle_rad, grey)
        Image-space elliptical occluders in front of the plate.
    subsamples : int
        ``N`` of the ``N x N`` supersampling of target edge pixels.

    Returns
    -------
    (height, width) uint8
    """
    ideal = render_ideal(
        camera,
        T_camera_target,
        diameter_m,
        levels=levels,
        plate_radius_m=plate_radius_m,
        background_grey=background_grey,
        extra_discs=extra_discs,
        subsamples=subsamples,
        blur_sigma_px=blur_sigma_px,
    )
    return finish_image(
        ideal,
        camera,
        blur_sigma_px=0.0,
        noise_sigma=noise_sigma,
        vignetting=vignetting,
        exposure=exposure,
        rng=rng,
        occluders=occluders,
    )
