"""Touch-up extraction: from frames + detections to the touch-up table.

Nothing in a recording marks where a touch-up starts or ends
(../shared/spec/recording.md); this stage finds them from the streams alone,
with the flange poses of the NOMINAL model (URDF in the recording, FK at the
joint vector interpolated at each image stamp):

1. **Segments.** Consecutive still captures whose flange poses differ by more
   than ``rot_split_rad`` in orientation or ``trans_split_m`` in position are
   separated by a large move: a new touch-up starts. (Probing shifts and loop
   steps are small pure translations of the flange.) A pure translation right
   after a segment's first capture never splits: it is the loop's first step,
   which can be long when the measuring pose was planned with the nominal robot
   (33 mm on a planned standard cell, where splitting there made a one-capture
   "touch-up" that took a target label of its own). A capture taken while
   moving joins the neighbouring still capture whose pose is nearer.
2. **Probing and loop.** Inside a segment, the loop starts at the last
   capture that returns to the segment's first pose after leaving it (the
   probing shifts come back to the base pose before the loop), else at the
   first capture. The final pose is that of the last still capture; the
   captures at that pose at the end of the segment are the repeated captures
   at convergence, and their detections are averaged.
3. **Image Jacobian.** Every pair of consecutive still captures with good
   detections whose flange poses differ by a small pure translation
   ``d_F = R_a^T (t_b - t_a)`` (flange frame) gives three equations
   ``m_b - m_a = J d_F`` for ``m = (u, v, s_inv)``; ``J`` (3 x 3) is fitted row
   by row by iteratively reweighted least squares (Huber) from every pair of
   the recording: the camera is fixed to the flange, so one matrix holds for
   every target. Only the size row depends on the target: ``s_inv = z / (f D)``
   scales with its printed diameter ``D``, so per target one scale ``c`` of
   that row is fitted from its own pairs and used where it differs from the
   median target's by more than ``size_row_sigmas`` of its standard error
   (:func:`size_row_scales`). A full Jacobian per target (the old rule) left
   each target's correction with its own 0.5-1.5 % error: per-target offsets
   of the corrected pin that no kinematic parameter can take (sRGB LR Mate-like
   seed 9: 0.064 mm shape against 0.026 mm with one matrix).
4. **Targets.** The virtual-pin point ``p`` (flange frame) is unknown, but all
   touch-ups of one target satisfy ``R_i p + t_i = c``. RANSAC over triples of
   two pairs of touch-ups (distinct orientations) each assumed to share a target
   solves ``(R_i - R_j) p = t_j - t_i``, ``(R_k - R_m) p = t_m - t_k``; the ``p``
   that makes most touch-ups coincide in pairs wins, is refined, and
   the points ``c_i = R_i p + t_i`` are grouped within ``group_radius_m``,
   labelled 0, 1, ... in first-touch order.
5. **Convergence and correction.** ``e_T = (u - u0, v - v0, 1/s - 1/s0)`` of
   the averaged final captures; converged when ``|u - u0|, |v - v0| <=
   threshold_px`` and ``|s - s0| <= threshold_size_px``. The residual
   correction is the flange translation that cancels ``e_T`` to first order:
   ``d_F = -J^{-1} e_T`` (the paper's touch-up step, section 2.1, applied once
   more on paper): at joint vector ``q`` the point ``p + d_F`` touched the target.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.kinematics.chain import fk, load_chain
from pipeline.kinematics.se3 import rotation_angle


@dataclass
class TouchupConfig:
    """Touch-up extraction settings (see module docstring for the steps)."""

    rot_split_rad: float = 0.01
    trans_split_m: float = 0.03
    same_pose_m: float = 2e-5
    same_pose_rad: float = 2e-4
    pure_translation_rad: float = 2e-4
    min_step_m: float = 5e-5
    max_step_m: float = 0.02
    group_radius_m: float = 0.02
    min_pairs_per_target: int = 6
    #: "global": one image Jacobian, its size row scaled per target where significant;
    #: "target": a full Jacobian per target with enough pairs (the first wave's rule)
    jacobian: str = "global"
    size_row_sigmas: float = 3.0
    default_threshold_px: float = 0.5
    default_threshold_size_px: float = 0.5
    ransac_samples: int = 400
    seed: int = 0
    tilt_correction: bool = True

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _rel(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle and flange-frame translation from pose a to pose b."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return float(rotation_angle(R)), T_a[:3, :3].T @ (T_b[:3, 3] - T_a[:3, 3])


def _huber_rows(X: np.ndarray, Y: np.ndarray, iters: int = 10) -> np.ndarray:
    """Row-wise robust fit of ``Y = X J^T``: ``X (N, 3)``, ``Y (N, 3)`` -> ``J (3, 3)``."""
    J = np.zeros((Y.shape[1], X.shape[1]))
    for r in range(Y.shape[1]):
        y = Y[:, r]
        w = np.ones(len(y))
        coef = np.zeros(X.shape[1])
        for _ in range(iters):
            sw = np.sqrt(w)
            coef, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
            res = y - X @ coef
            sc = 1.4826 * float(np.median(np.abs(res))) + 1e-15
            k = 1.5 * sc
            a = np.abs(res)
            w = np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
        J[r] = coef
    return J


def estimate_jacobian(dF: np.ndarray, dm: np.ndarray) -> np.ndarray | None:
    """Image Jacobian from pairs: ``dm (N, 3) ~ J dF (N, 3)``; None if ill-posed.

    Parameters
    ----------
    dF : (N, 3) flange-frame translations (m)
    dm : (N, 3) changes of ``(u, v, s_inv)`` (px, px, 1/px)

    Returns
    -------
    (3, 3) ``J`` with ``dm = J dF``, or None with fewer than 4 pairs or
    translations that do not span 3-D (singular value ratio < 0.05).
    """
    if len(dF) < 4:
        return None
    sv = np.linalg.svd(dF, compute_uv=False)
    if sv[-1] < 0.05 * sv[0]:
        return None
    return _huber_rows(dF, dm)


def _group_targets(Ts: np.ndarray, config: TouchupConfig) -> tuple[np.ndarray, np.ndarray]:
    """Label touch-ups by target from their final flange poses (module docstring, step 4).

    Returns labels ``(n,)`` (0, 1, ... in first-touch order) and the pin estimate ``p (3,)``.
    """
    n = len(Ts)
    if n == 1:
        return np.zeros(1, dtype=np.int64), np.zeros(3)
    R = Ts[:, :3, :3]
    t = Ts[:, :3, 3]
    ang = rotation_angle(np.einsum("iba,jbc->ijac", R, R))  # angle of R_i^T R_j
    rng = np.random.default_rng(config.seed)
    eps = config.group_radius_m * 0.25

    def score(p: np.ndarray) -> tuple[int, float]:
        c = R @ p + t
        d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=-1)
        ok = (d < eps) & (ang > 0.05)
        return int(ok.any(axis=1).sum()), float(np.sum(np.minimum(d, eps)))

    best_p = np.zeros(3)
    best = (-1, np.inf)
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if ang[i, j] > 0.05]
    # hypotheses: two pairs assumed to share a target each (6 equations, 3 unknowns);
    # every combination of pairs of consecutive touch-ups first (runs usually touch
    # one target several times in a row), then random combinations of any pairs
    adjacent = [pq for pq in pairs if pq[1] == pq[0] + 1]
    hyps: list[tuple[tuple[int, int], tuple[int, int]]] = [
        (adjacent[x], adjacent[y])
        for x in range(len(adjacent))
        for y in range(x + 1, len(adjacent))
    ][: 4 * config.ransac_samples]
    if len(pairs) > 1:
        n_pp = len(pairs) * (len(pairs) - 1) // 2
        if n_pp <= config.ransac_samples:
            hyps += [
                (pairs[x], pairs[y]) for x in range(len(pairs)) for y in range(x + 1, len(pairs))
            ]
        else:
            for _ in range(config.ransac_samples):
                x, y = rng.choice(len(pairs), size=2, replace=False)
                hyps.append((pairs[int(x)], pairs[int(y)]))
    elif pairs:
        hyps.append((pairs[0], pairs[0]))
    for (i, j), (k, m) in hyps:
        A = np.concatenate([R[i] - R[j], R[k] - R[m]])
        b = np.concatenate([t[j] - t[i], t[m] - t[k]])
        p, *_ = np.linalg.lstsq(A, b, rcond=None)
        sc = score(p)
        if sc[0] > best[0] or (sc[0] == best[0] and sc[1] < best[1]):
            best, best_p = sc, p
    labels = _cluster(R @ best_p + t, config.group_radius_m)
    # refine p with the groups: R_i p + t_i = c_g for every member
    for _ in range(2):
        rows, rhs = [], []
        for g in np.unique(labels):
            idx = np.nonzero(labels == g)[0]
            if len(idx) < 2:
                continue
            Rm = R[idx].mean(axis=0)
            tm = t[idx].mean(axis=0)
            for ii in idx:
                rows.append(R[ii] - Rm)
                rhs.append(tm - t[ii])
        if not rows:
            break
        p_new, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
        if not np.all(np.isfinite(p_new)):
            break
        best_p = p_new
        labels = _cluster(R @ best_p + t, config.group_radius_m)
    return labels, best_p


def _cluster(c: np.ndarray, radius: float) -> np.ndarray:
    """Greedy grouping in order: join the nearest existing group centre within ``radius``."""
    labels = np.full(len(c), -1, dtype=np.int64)
    centres: list[list[np.ndarray]] = []
    for i, ci in enumerate(c):
        if centres:
            d = [np.linalg.norm(ci - np.mean(g, axis=0)) for g in centres]
            k = int(np.argmin(d))
            if d[k] < radius:
                labels[i] = k
                centres[k].append(ci)
                continue
        labels[i] = len(centres)
        centres.append([ci])
    return labels


def size_row_scales(
    J: np.ndarray,
    dF: np.ndarray,
    dm: np.ndarray,
    groups: np.ndarray,
    *,
    sigmas: float,
    min_pairs: int,
) -> tuple[float, dict[int, tuple[float, float]]]:
    """Per-target scale of the image Jacobian's size row, with its standard error.

    A target of printed diameter ``D_k`` seen at the designated size has
    ``s_inv = z / (f D_k)``, so its size row is a common row times ``1 / D_k``;
    the centre rows do not depend on the target. Per target the least-squares
    scale of its pairs' size changes against the pooled row ``J_2``,

        c_k = sum(a_i b_i) / sum(a_i^2),  a_i = J_2 . dF_i,  b_i = dm_i,2,
        se(c_k) = sqrt(sum(r_i^2) / (n - 1) / sum(a_i^2)),

    is taken relative to the median target's, ``c_ref = median_k c_k`` (the
    pooled row mixes every print; the median is the prints that agree), and is
    kept where ``|c_k / c_ref - 1| > sigmas * se(c_k)``: a print measurably
    larger or smaller than the others. The rest take ``c_ref J_2``.

    Parameters
    ----------
    J : (3, 3) global image Jacobian
    dF : (N, 3) flange translations of the pairs (m)
    dm : (N, 3) their ``(u, v, s_inv)`` changes
    groups : (N,) target label of each pair

    Returns
    -------
    c_ref : the scale of the size row the targets share (1.0 with fewer than 2 targets)
    kept : ``{label: (c_k / c_ref, se)}`` for the targets whose own scale is kept
    """
    raw: dict[int, tuple[float, float]] = {}
    a_all = dF @ J[2]
    for g in np.unique(groups):
        m = groups == g
        if int(m.sum()) < min_pairs:
            continue
        a, b = a_all[m], dm[m, 2]
        saa = float(a @ a)
        if saa <= 0.0:
            continue
        c = float(a @ b) / saa
        r = b - c * a
        raw[int(g)] = (c, float(np.sqrt(float(r @ r) / max(len(a) - 1, 1) / saa)))
    if len(raw) < 2:
        return 1.0, {}
    c_ref = float(np.median([c for c, _ in raw.values()]))
    kept = {
        g: (c / c_ref, se / c_ref)
        for g, (c, se) in raw.items()
        if abs(c / c_ref - 1.0) > sigmas * se / c_ref
    }
    return c_ref, kept


def camera_from_jacobian(J: np.ndarray, s0: float) -> tuple[np.ndarray, float, float]:
    """Camera orientation in the flange frame, focal length and stand-off from ``J``.

    A flange translation ``d`` moves the target by ``-R_camera_flange d`` in the
    camera frame, so near the optical axis ``du = -(f/z) (R_cf d)_x``,
    ``dv = -(f/z) (R_cf d)_y``: the first two rows of ``J`` are ``-(f/z)`` times
    the first two rows of ``R_cf``. With ``s = f D / z``, ``s_inv = z / (f D)`` and
    ``d s_inv / dz = 1 / (f D)``, so ``z = s_inv / |J_2|`` (the third row's norm).

    Returns
    -------
    R_flange_camera : (3, 3)
    f_px : float, focal length in pixels (nominal-model metres)
    z_m : float, stand-off at the designated size
    """
    gx = float(np.linalg.norm(J[0]))
    gy = float(np.linalg.norm(J[1]))
    rx = -J[0] / gx
    ry = -J[1] / gy
    M = np.stack([rx, ry, np.cross(rx, ry)])
    U, _, Vt = np.linalg.svd(M)
    R_cf = U @ Vt
    z = (1.0 / s0) / float(np.linalg.norm(J[2]))
    f = 0.5 * (gx + gy) * z
    return R_cf.T, f, z


def diameter_from_jacobian(J: np.ndarray, s0: float) -> float:
    """The printed target diameter the image Jacobian implies, ``D = s_0 / g`` (m).

    With ``g = f / z`` the image motion per metre of lateral flange translation
    (the mean norm of ``J``'s first two rows, :func:`camera_from_jacobian`) and
    the long axis at the designated size ``s_0 = f D / z``, ``D = s_0 z / f =
    s_0 / g``. The focal length and stand-off cancel; what is left is in the
    nominal robot's metres. Near-axis approximation: off-axis views and lens
    distortion leave it ~1 % off (shipped and conformance samples: 0.3-1.1 %).

    Parameters
    ----------
    J : (3, 3) image Jacobian, rows ``(du, dv, ds_inv)`` per metre of flange translation
    s0 : designated long axis, px
    """
    g = 0.5 * (float(np.linalg.norm(J[0])) + float(np.linalg.norm(J[1])))
    return float(s0) / g if g > 0 else float("nan")


def view_geometry(J: np.ndarray, s0: float, angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a print-size error does to a touch-up, from the image Jacobian (flange frame).

    A target whose image long axis reads ``(1 + eps)`` times what a perfect disc of
    the nominal diameter would show stops the camera ``z eps`` too far (``s = f D / z``),
    so the point that touched the target is ``p_pin + d + eps g`` with

        g = z r_z                                   (m per unit eps)

    ``r_z`` the camera's view axis and ``z`` the stand-off
    (:func:`camera_from_jacobian`). The long axis of touch-up ``k`` lies along

        l_k = cos(a_k) r_x + sin(a_k) r_y           (unit)

    ``a_k`` its image long-axis angle (from ``+u`` towards ``+v``): what
    :mod:`pipeline.stages.print_shape` needs to tell an out-of-round print from the
    roll of the view.

    Returns
    -------
    g : (3,) ; l : (n, 3) (NaN where the angle is)
    """
    R_fc, _, z = camera_from_jacobian(J, s0)
    g = z * R_fc[:, 2]
    a = np.asarray(angle, dtype=float)
    lvec = np.cos(a)[:, None] * R_fc[:, 0][None, :] + np.sin(a)[:, None] * R_fc[:, 1][None, :]
    return g, lvec


def tilt_bias(
    shape: np.ndarray,
    T_base_flange: np.ndarray,
    labels: np.ndarray,
    J: np.ndarray,
    s0: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets between the ellipse and the projected circle centre / untilted size.

    A circle of radius ``R`` at distance ``z`` whose plane is tilted by ``theta``
    images as an ellipse with ``b / a = cos(theta)`` (``a = f R / z``), whose centre
    lies off the image of the circle's centre by ``(a^2 / f) sin(theta) cos(theta)``
    along the minor axis, away from the side the plate normal leans to, and
    whose long axis exceeds ``f 2R / z`` by ``s (a / f)^2 sin^2(theta) / 2`` (second
    order expansion of the perspective projection of the tilted circle).
    ``f`` comes from the image Jacobian (:func:`camera_from_jacobian`). Which end
    of the minor axis the normal leans to is ambiguous in one image; the sign
    is chosen per target so that the plate normals of all its touch-ups agree
    in the base frame (nominal flange orientations, camera orientation from ``J``).

    Parameters
    ----------
    shape : (n, 5) per touch-up: u, v, s, s_minor, long-axis angle (NaN if lost)
    T_base_flange : (n, 4, 4) nominal flange poses at the final captures
    labels : (n,) target labels
    J : (3, 3) image Jacobian
    s0 : designated size

    Returns
    -------
    bias : (n, 3) ``(du, dv, ds)``: add du, dv to the ellipse centre, subtract ds
        from its long axis (0 where not resolved)
    tilt_deg : (n,) tilt of the plate from the image (NaN if lost)
    resolved : (n,) the sign was resolved (at least two touch-ups of the target
        with distinct orientations, or a negligible tilt)
    """
    n = len(shape)
    bias = np.zeros((n, 3))
    resolved = np.zeros(n, dtype=bool)
    ok = np.all(np.isfinite(shape), axis=1)
    a = 0.5 * shape[:, 2]
    b = 0.5 * shape[:, 3]
    cos_t = np.clip(np.where(ok, b / np.where(ok, a, 1.0), 1.0), 0.0, 1.0)
    sin_t = np.sqrt(1.0 - cos_t**2)
    tilt_deg = np.where(ok, np.degrees(np.arccos(cos_t)), np.nan)
    try:
        R_fc, f, _ = camera_from_jacobian(J, s0)
    except (np.linalg.LinAlgError, ValueError):
        return bias, tilt_deg, resolved
    if not np.isfinite(f) or f <= 0:
        return bias, tilt_deg, resolved
    phi = shape[:, 4]
    m = np.stack([-np.sin(phi), np.cos(phi)], axis=1)  # minor-axis direction (u, v)
    n_cam = np.stack([sin_t * m[:, 0], sin_t * m[:, 1], -cos_t], axis=1)
    n_base = np.einsum("nij,jk,nk->ni", T_base_flange[:, :3, :3], R_fc, np.nan_to_num(n_cam))
    n_flip = np.einsum(
        "nij,jk,nk->ni",
        T_base_flange[:, :3, :3],
        R_fc,
        np.nan_to_num(n_cam * np.array([-1.0, -1.0, 1.0])),
    )
    sign = np.ones(n)
    for g in np.unique(labels):
        idx = [int(i) for i in np.nonzero((labels == g) & ok)[0]]
        if not idx:
            continue
        if len(idx) == 1:
            resolved[idx[0]] = bool(tilt_deg[idx[0]] < 2.0)
            continue
        best, best_sc = None, -1.0
        if len(idx) <= 10:
            for code in range(1 << len(idx)):
                sg = np.array([(-1.0 if (code >> jj) & 1 else 1.0) for jj in range(len(idx))])
                vecs = np.where(sg[:, None] > 0, n_base[idx], n_flip[idx])
                sc = float(np.linalg.norm(vecs.sum(axis=0)))
                if sc > best_sc:
                    best, best_sc = sg, sc
        else:
            sg = np.ones(len(idx))
            for _ in range(5):
                for j in range(len(idx)):
                    rest = np.where(sg[:, None] > 0, n_base[idx], n_flip[idx]).sum(axis=0)
                    rest -= n_base[idx[j]] if sg[j] > 0 else n_flip[idx[j]]
                    sg[j] = 1.0 if n_base[idx[j]] @ rest >= n_flip[idx[j]] @ rest else -1.0
            best = sg
        assert best is not None
        sign[idx] = best
        resolved[idx] = True
    shift = (a**2 / f) * sin_t * cos_t
    bias[:, 0] = np.where(ok & resolved, sign * shift * m[:, 0], 0.0)
    bias[:, 1] = np.where(ok & resolved, sign * shift * m[:, 1], 0.0)
    bias[:, 2] = np.where(ok, shape[:, 2] * (a / f) ** 2 * sin_t**2 / 2.0, 0.0)
    return bias, tilt_deg, resolved


def _meta_float(meta: dict[str, str], key: str) -> float | None:
    v = meta.get(key)
    if v is None or str(v).strip() == "":
        return None
    try:
        x = float(v)
    except ValueError as exc:
        raise BadInput(f"touchup metadata {key}={v!r} is not a number") from exc
    if not np.isfinite(x):
        raise BadInput(f"touchup metadata {key}={v!r} is not a finite number")
    if key not in ("designated_u", "designated_v") and x <= 0:
        raise BadInput(f"touchup metadata {key}={v!r} must be > 0")
    return x


def extract_touchups(
    frames: pd.DataFrame,
    detections: pd.DataFrame,
    info: Any,
    config: TouchupConfig,
) -> pd.DataFrame:
    """Find, group and correct the touch-ups of a recording.

    Parameters
    ----------
    frames : frames artefact (one row per image, joint columns)
    detections : detections artefact (same ``frame_index``)
    info : RecordingInfo (urdf, metadata, joint names, base/flange links)
    config : TouchupConfig

    Returns
    -------
    DataFrame per ``schemas/touchups.json``: one row per touch-up (converged
    or not), with ``target_id``, the correction ``dx/dy/dz_flange`` (m), the
    joint columns (converged joint vector), the ``e_T`` history and quality
    flags. ``df.attrs`` holds ``image_jacobian`` (3 x 3 nested list, global),
    ``pin_estimate_flange`` and the designated values used.
    """
    meta = dict(info.metadata)
    inferred = getattr(info, "inferred", {})
    names = list(info.joint_names)
    df = frames.merge(detections, on="frame_index", how="left", suffixes=("", "_det"))
    df = df.sort_values("frame_index").reset_index(drop=True)
    n = len(df)
    if n == 0:
        raise BadInput(f"{info.path}: no images to extract touch-ups from")
    chain = load_chain(info.urdf, info.base_link, info.flange_link)
    Q = df[names].to_numpy(dtype=float)
    T = fk(chain, Q)
    found = df["found"].fillna(False).to_numpy(bool)
    good = found & df["quality_ok"].fillna(False).to_numpy(bool)
    still = ~df["moving"].to_numpy(bool) & ~df["joint_gap"].to_numpy(bool)
    u = df["u"].to_numpy(float)
    v = df["v"].to_numpy(float)
    s = df["s"].to_numpy(float)

    # 1. segments
    seg = np.full(n, -1, dtype=np.int64)
    still_idx = np.nonzero(still)[0]
    if len(still_idx) == 0:
        raise BadInput(f"{info.path}: every capture was taken while the arm moved")
    cur = 0
    seg[still_idx[0]] = 0
    n_cur = 1  # still captures in the current segment
    for a, b in zip(still_idx[:-1], still_idx[1:], strict=True):
        ang, d = _rel(T[a], T[b])
        # a pure translation after a lone first capture is the loop's first step, however
        # long (a plan made with the nominal robot can start 30+ mm off)
        far = np.linalg.norm(d) > config.trans_split_m and n_cur > 1
        if ang > config.rot_split_rad or far:
            cur += 1
            n_cur = 0
        seg[b] = cur
        n_cur += 1
    for i in np.nonzero(~still)[0]:
        prev = still_idx[still_idx < i]
        nxt = still_idx[still_idx > i]
        cand = []
        for j in [int(x) for x in prev[-1:]] + [int(x) for x in nxt[:1]]:
            ang, d = _rel(T[j], T[i])
            cand.append((ang * 0.2 + np.linalg.norm(d), j))
        seg[i] = seg[min(cand)[1]] if cand else 0

    # designated values
    u0 = _meta_float(meta, "designated_u")
    v0 = _meta_float(meta, "designated_v")
    s0 = _meta_float(meta, "designated_size_px")
    thr = _meta_float(meta, "threshold_px")
    thr_s = _meta_float(meta, "threshold_size_px")
    n_seg = int(seg.max()) + 1
    seg_frames = [np.nonzero(seg == k)[0] for k in range(n_seg)]

    def final_block(fr: np.ndarray) -> np.ndarray:
        st = [i for i in fr if still[i]]
        if not st:
            return np.array([], dtype=np.int64)
        last = st[-1]
        block = [last]
        for i in reversed(st[:-1]):
            ang, d = _rel(T[last], T[i])
            if ang < config.same_pose_rad and np.linalg.norm(d) < config.same_pose_m:
                block.insert(0, i)
            else:
                break
        return np.array(block, dtype=np.int64)

    finals = [final_block(fr) for fr in seg_frames]
    if s0 is None or "designated_u" in inferred:
        fin_good = np.array([i for b in finals for i in b if good[i]], dtype=np.int64)
        if len(fin_good):
            if s0 is None:
                s0 = float(np.median(s[fin_good]))
                meta["designated_size_px"] = repr(s0)
                inferred["designated_size_px"] = f"{s0:.3f} (median size at the final captures)"
            if "designated_u" in inferred:
                u0 = float(np.median(u[fin_good]))
                v0 = float(np.median(v[fin_good]))
                meta["designated_u"], meta["designated_v"] = repr(u0), repr(v0)
                inferred["designated_u"] = f"{u0:.3f} (median centre at the final captures)"
                inferred["designated_v"] = f"{v0:.3f} (median centre at the final captures)"
    if u0 is None or v0 is None or s0 is None:
        raise BadInput(f"{info.path}: cannot infer the designated centre/size (no detections)")
    if thr is None:
        thr = config.default_threshold_px
        meta["threshold_px"] = repr(thr)
        inferred["threshold_px"] = f"{thr} (default)"
    if thr_s is None:
        thr_s = config.default_threshold_size_px
        meta["threshold_size_px"] = repr(thr_s)
        inferred["threshold_size_px"] = f"{thr_s} (default)"

    # 2. loop starts
    loop_start = []
    for fr in seg_frames:
        st = [i for i in fr if still[i]]
        start = fr[0]
        if st:
            away = False
            for i in st[1:]:
                ang, d = _rel(T[st[0]], T[i])
                at_first = ang < config.same_pose_rad and np.linalg.norm(d) < config.same_pose_m
                if not at_first:
                    away = True
                elif away:
                    start = i
                    away = False
        loop_start.append(int(start))

    # 3. Jacobian pairs (consecutive still good captures within a segment)
    pairs: list[tuple[int, np.ndarray, np.ndarray]] = []
    for k, fr in enumerate(seg_frames):
        st = [i for i in fr if still[i] and good[i]]
        for a, b in zip(st[:-1], st[1:], strict=False):
            ang, d = _rel(T[a], T[b])
            step = float(np.linalg.norm(d))
            if ang < config.pure_translation_rad and config.min_step_m < step < config.max_step_m:
                dm = np.array([u[b] - u[a], v[b] - v[a], 1.0 / s[b] - 1.0 / s[a]])
                pairs.append((k, d, dm))
    if not pairs:
        raise BadInput(
            f"{info.path}: no two still captures differ by a small pure flange translation: "
            "the image Jacobian cannot be estimated"
        )
    dF_all = np.array([p[1] for p in pairs])
    dm_all = np.array([p[2] for p in pairs])
    J_global = estimate_jacobian(dF_all, dm_all)
    if J_global is None:
        raise BadInput(
            f"{info.path}: the small flange translations ({len(pairs)} pairs) do not span "
            "three directions: the image Jacobian cannot be estimated"
        )

    # 4. targets from final (or last seen) poses
    rep = []
    for k, fr in enumerate(seg_frames):
        b = finals[k]
        pick = [int(i) for i in b if found[i]] or [int(i) for i in fr if still[i] and found[i]]
        pick = pick or [int(i) for i in fr if still[i]] or [int(i) for i in fr]
        rep.append(pick[-1])
    labels, p_pin = _group_targets(T[np.array(rep)], config)
    seg_pairs: dict[int, list[int]] = {}
    for ip, (k, _, _) in enumerate(pairs):
        seg_pairs.setdefault(int(labels[k]), []).append(ip)
    J_target: dict[int, np.ndarray] = {}
    if config.jacobian == "target":
        for g, members in seg_pairs.items():
            if len(members) >= config.min_pairs_per_target:
                Jg = estimate_jacobian(dF_all[members], dm_all[members])
                if Jg is not None and np.all(np.isfinite(Jg)):
                    J_target[g] = Jg
    elif config.jacobian == "global":
        pair_group = np.array([int(labels[p[0]]) for p in pairs])
        c_ref, scales = size_row_scales(
            J_global,
            dF_all,
            dm_all,
            pair_group,
            sigmas=config.size_row_sigmas,
            min_pairs=config.min_pairs_per_target,
        )
        J_global = J_global * np.array([[1.0], [1.0], [c_ref]])
        for g, (c, _) in scales.items():
            J_target[g] = J_global * np.array([[1.0], [1.0], [c]])
    else:
        raise BadInput(f"touchups: jacobian must be 'global' or 'target', not {config.jacobian!r}")

    # 5. averaged final captures, the tilt bias, then one row per touch-up
    s_minor = df["s_minor"].to_numpy(float)
    ang2 = 2.0 * df["angle"].to_numpy(float)
    uses = []
    shape = np.full((n_seg, 5), np.nan)  # u, v, s, s_minor, long-axis angle
    for k in range(n_seg):
        b = finals[k]
        use_k = [int(i) for i in b if good[i]] or [int(i) for i in b if found[i]]
        uses.append(use_k)
        if use_k:
            shape[k] = [
                np.mean(u[use_k]),
                np.mean(v[use_k]),
                np.mean(s[use_k]),
                np.mean(s_minor[use_k]),
                0.5 * np.arctan2(np.mean(np.sin(ang2[use_k])), np.mean(np.cos(ang2[use_k]))),
            ]
    T_rep = np.array([T[uses[k][-1]] if uses[k] else T[rep[k]] for k in range(n_seg)])
    bias, tilt_deg, resolved = tilt_bias(shape, T_rep, labels, J_global, s0)
    if not config.tilt_correction:
        bias[:] = 0.0
    view_g, axis_l = view_geometry(J_global, s0, shape[:, 4])
    out: list[dict[str, Any]] = []
    for k, fr in enumerate(seg_frames):
        b = finals[k]
        avg = [i for i in b if good[i]]
        avg_found = [i for i in b if found[i]]
        use = avg or avg_found
        lost = len(use) == 0
        loop_fr = [i for i in fr if i >= loop_start[k]]
        hist = [i for i in loop_fr if found[i]]
        row: dict[str, Any] = {
            "touchup_id": k,
            "target_id": int(labels[k]),
            "lost": lost,
            "first_frame": int(fr[0]),
            "last_frame": int(fr[-1]),
            "loop_start_frame": int(loop_start[k]),
            "n_probe_frames": int(sum(1 for i in fr if i < loop_start[k])),
            "frame_indices": [int(i) for i in fr],
            "converged_frame_indices": [int(i) for i in use],
            "n_captures": len(fr),
            "n_converged_captures": len(avg),
            "n_iterations": int(max(len({_pose_key(T[i]) for i in loop_fr if still[i]}) - 1, 0)),
            "moving": bool(len(b) == 0),
            "e_u_history": [float(u[i] - u0) for i in hist],
            "e_v_history": [float(v[i] - v0) for i in hist],
            "e_s_history": [float(s[i] - s0) for i in hist],
        }
        ref = use if use else (list(b) if len(b) else [int(fr[-1])])
        q = Q[ref].mean(axis=0)
        for j, nm in enumerate(names):
            row[nm] = float(q[j])
        row["stamp_ns"] = int(df["stamp_ns"].iloc[ref[-1]])
        Jk = J_target.get(int(labels[k]), J_global)
        row["jacobian_source"] = "target" if int(labels[k]) in J_target else "global"
        if lost:
            mu = mv = ms = float("nan")
            row.update(converged=False, dx_flange=0.0, dy_flange=0.0, dz_flange=0.0)
        else:
            mu = float(np.mean(u[use]))
            mv = float(np.mean(v[use]))
            ms = float(np.mean(s[use]))
            conv = abs(mu - u0) <= thr and abs(mv - v0) <= thr and abs(ms - s0) <= thr_s
            # the image of the circle's centre, and the size an untilted target would show
            mu_c, mv_c, ms_c = mu + bias[k, 0], mv + bias[k, 1], ms - bias[k, 2]
            e_T = np.array([mu_c - u0, mv_c - v0, 1.0 / ms_c - 1.0 / s0])
            try:
                d = -np.linalg.solve(Jk, e_T)
            except np.linalg.LinAlgError:
                d = np.zeros(3)
            row.update(
                converged=bool(conv),
                dx_flange=float(d[0]),
                dy_flange=float(d[1]),
                dz_flange=float(d[2]),
            )
        row.update(
            u=mu,
            v=mv,
            s=ms,
            e_u=mu - u0,
            e_v=mv - v0,
            e_s_px=ms - s0,
            e_sinv=(1.0 / ms - 1.0 / s0) if np.isfinite(ms) else float("nan"),
            fit_residual_px=float(np.max(df["residual_px"].to_numpy(float)[use]))
            if use
            else float("nan"),
            border_contact=bool(np.any(df["border_contact"].fillna(False).to_numpy(bool)[use]))
            if use
            else False,
            ambiguous=bool(np.any(df["ambiguous"].fillna(False).to_numpy(bool)[use]))
            if use
            else False,
            weight=1.0,
            tilt_deg=float(tilt_deg[k]),
            tilt_resolved=bool(resolved[k]),
            bias_u_px=float(bias[k, 0]),
            bias_v_px=float(bias[k, 1]),
            bias_s_px=float(bias[k, 2]),
            view_gx=float(view_g[0]),
            view_gy=float(view_g[1]),
            view_gz=float(view_g[2]),
            axis_lx=float(axis_l[k, 0]),
            axis_ly=float(axis_l[k, 1]),
            axis_lz=float(axis_l[k, 2]),
        )
        out.append(row)
    table = pd.DataFrame(out)
    # stable column order: declared first, then extras
    table.attrs["image_jacobian"] = J_global.tolist()
    table.attrs["image_jacobian_per_target"] = {int(g): J.tolist() for g, J in J_target.items()}
    table.attrs["pin_estimate_flange"] = p_pin.tolist()
    table.attrs["designated"] = {
        "u": u0,
        "v": v0,
        "s": s0,
        "threshold_px": thr,
        "threshold_size_px": thr_s,
    }
    table.attrs["n_jacobian_pairs"] = len(pairs)
    table.attrs["implied_target_diameter_m"] = diameter_from_jacobian(J_global, s0)
    return table


def _pose_key(T: np.ndarray) -> tuple[int, int, int]:
    """Position rounded to 20 um: captures at one pose share the key."""
    p = np.round(T[:3, 3] / 2e-5).astype(int)
    return int(p[0]), int(p[1]), int(p[2])
