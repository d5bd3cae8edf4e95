"""Touch-up extraction: from frames + detections to the touch-up table.

Nothing in a recording marks where a touch-up starts or ends
(spec/recording.md); this stage finds them from the streams alone,
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
   at convergence, and their detections are averaged (the early ones weighing
   less when they scatter more: a camera still swinging, :mod:`touchup_settle`;
   the centre then freed of the swing left in the last one by a one-mode fit,
   :mod:`touchup_swing`).
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

The code of the steps (:func:`extract_touchups` calls them in order): the
segments, the final pose and the loop start in
:mod:`pipeline.stages.touchups.segments`; the image Jacobian and the camera it
implies in :mod:`pipeline.stages.touchups.jacobian`; the targets in
:mod:`pipeline.stages.touchups.targets`; the tilt bias of a tilted target's
ellipse, applied before the correction, in :mod:`pipeline.stages.touchups.tilt`;
the designated values, the Jacobian pairs, convergence and correction, and the
table's rows here.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.estimation.correction_frame import scatter_columns
from pipeline.kinematics.chain import fk, load_chain
from pipeline.measurement.image import diameter_from_jacobian, pair_change, view_geometry
from pipeline.measurement.image_jacobian import fit_image_jacobian
from pipeline.stages.touchups.jacobian import pair_scatters, size_row_scales
from pipeline.stages.touchups.noise import capture_noise, pose_noise
from pipeline.stages.touchups.rows import final_shapes, touchup_row
from pipeline.stages.touchups.segments import final_block, loop_starts, relative_poses, segments
from pipeline.stages.touchups.servo_target import ServoTarget, loop_steps, servo_target
from pipeline.stages.touchups.targets import group_targets
from pipeline.stages.touchups.tilt import tilt_bias
from pipeline.stages.touchups.types import Captures, Designated, Tilt

#: the public names of touch-up extraction, importable from here (the image
#: Jacobian and the tilt bias live in touchup_jacobian and touchup_tilt; what a
#: Jacobian implies of the camera, in pipeline.measurement.image)
__all__ = [
    "TouchupConfig",
    "extract_touchups",
    "size_row_scales",
    "tilt_bias",
]


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
    #: scale each pair's centre-row change to the designated size (``f / z = s / D``):
    #: pairs taken away from the stand-off (the approach's probes) then give the centre
    #: rows at the converged depth, where the residual correction applies
    depth_scaled_jacobian: bool = True
    default_threshold_px: float = 0.5
    default_threshold_size_px: float = 0.5
    ransac_samples: int = 400
    seed: int = 0
    tilt_correction: bool = True
    #: designated values missing from the metadata read from the loops' steps (D1)-(D2)
    #: rather than the medians at the final captures
    designated_from_steps: bool = True

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


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


def _captures(frames: pd.DataFrame, detections: pd.DataFrame, info: Any) -> Captures:
    """Frames joined with detections in frame order, with the nominal flange poses."""
    names = list(info.joint_names)
    df = frames.merge(detections, on="frame_index", how="left", suffixes=("", "_det"))
    df = df.sort_values("frame_index").reset_index(drop=True)
    if len(df) == 0:
        raise BadInput(f"{info.path}: no images to extract touch-ups from")
    chain = load_chain(info.urdf, info.base_link, info.flange_link)
    Q = df[names].to_numpy(dtype=float)
    found = df["found"].fillna(False).to_numpy(bool)
    return Captures(
        df=df,
        names=names,
        Q=Q,
        T=fk(chain, Q),
        found=found,
        good=found & df["quality_ok"].fillna(False).to_numpy(bool),
        still=~df["moving"].to_numpy(bool) & ~df["joint_gap"].to_numpy(bool),
        u=df["u"].to_numpy(float),
        v=df["v"].to_numpy(float),
        s=df["s"].to_numpy(float),
    )


def _designated_attrs(des: Designated, aim: ServoTarget | None) -> dict[str, Any]:
    """The designated values used, and the loops' own aim beside them (its offset from
    them: the loop's measure told from vtcal's), for the table's metadata."""
    out: dict[str, Any] = {
        "u": des.u0,
        "v": des.v0,
        "s": des.s0,
        "threshold_px": des.thr,
        "threshold_size_px": des.thr_s,
    }
    if aim is not None:
        used = np.array([des.u0, des.v0, des.s0])
        out["loop_aim"] = {
            "u": float(aim.m0[0]),
            "v": float(aim.m0[1]),
            "s": float(aim.m0[2]),
            "sd_px": [float(x) for x in aim.sd],
            "minus_used_px": [float(x) for x in aim.m0 - used],
            "n_steps": aim.n_steps,
            "gain": aim.gain,
        }
    return out


def _loop_aim(loops: list[np.ndarray], c: Captures, config: TouchupConfig) -> ServoTarget | None:
    """Where the touch-up loops aimed, read from their steps (:mod:`.servo_target`, (D1)-(D2)).

    It stands in for designated values the recording lacks, and beside declared ones it
    tells the loop's own measure from vtcal's: a loop whose detector reads the size
    ``b`` px differently from vtcal's aims ``b`` px off the declared size in vtcal's
    measure (touchups.parquet's ``designated`` metadata keeps both).
    """
    if not config.designated_from_steps:
        return None
    m = np.stack([c.u, c.v, c.s], axis=1)
    mk, dm = loop_steps(loops, c.T, m, config.same_pose_rad, config.same_pose_m)
    return servo_target(mk, dm)


def _designated(
    meta: dict[str, str],
    inferred: dict[str, str],
    finals: list[np.ndarray],
    c: Captures,
    config: TouchupConfig,
    path: Any,
    aim: ServoTarget | None = None,
) -> Designated:
    """The designated centre and size and the thresholds: from the metadata, else inferred.

    A size missing from the metadata, and a centre ``inferred`` marks as guessed,
    are where the loops aimed (``aim``, :func:`_loop_aim`), or, when the steps
    cannot tell (too few, or no contracting loop),
    the medians at the good final captures; a missing threshold is the
    config's default. What is inferred is written to ``meta`` and ``inferred``.
    """
    u0 = _meta_float(meta, "designated_u")
    v0 = _meta_float(meta, "designated_v")
    s0 = _meta_float(meta, "designated_size_px")
    thr = _meta_float(meta, "threshold_px")
    thr_s = _meta_float(meta, "threshold_size_px")
    if s0 is None or "designated_u" in inferred:
        fin_good = np.array([i for b in finals for i in b if c.good[i]], dtype=np.int64)
        if aim is not None:
            how = f"where the loops aimed, from {aim.n_steps} loop steps"
            if s0 is None:
                s0 = float(aim.m0[2])
                meta["designated_size_px"] = repr(s0)
                inferred["designated_size_px"] = f"{s0:.3f} ({how}, +- {aim.sd[2]:.3f})"
            if "designated_u" in inferred:
                u0, v0 = float(aim.m0[0]), float(aim.m0[1])
                meta["designated_u"], meta["designated_v"] = repr(u0), repr(v0)
                inferred["designated_u"] = f"{u0:.3f} ({how}, +- {aim.sd[0]:.3f})"
                inferred["designated_v"] = f"{v0:.3f} ({how}, +- {aim.sd[1]:.3f})"
        elif len(fin_good):
            if s0 is None:
                s0 = float(np.median(c.s[fin_good]))
                meta["designated_size_px"] = repr(s0)
                inferred["designated_size_px"] = f"{s0:.3f} (median size at the final captures)"
            if "designated_u" in inferred:
                u0 = float(np.median(c.u[fin_good]))
                v0 = float(np.median(c.v[fin_good]))
                meta["designated_u"], meta["designated_v"] = repr(u0), repr(v0)
                inferred["designated_u"] = f"{u0:.3f} (median centre at the final captures)"
                inferred["designated_v"] = f"{v0:.3f} (median centre at the final captures)"
    if u0 is None or v0 is None or s0 is None:
        raise BadInput(f"{path}: cannot infer the designated centre/size (no detections)")
    if thr is None:
        thr = config.default_threshold_px
        meta["threshold_px"] = repr(thr)
        inferred["threshold_px"] = f"{thr} (default)"
    if thr_s is None:
        thr_s = config.default_threshold_size_px
        meta["threshold_size_px"] = repr(thr_s)
        inferred["threshold_size_px"] = f"{thr_s} (default)"
    return Designated(u0, v0, s0, thr, thr_s)


def _jacobian_pairs(
    seg_frames: list[np.ndarray],
    c: Captures,
    config: TouchupConfig,
    path: Any,
    des: Designated,
    p_pin: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 3: the pairs and the global image Jacobian they give.

    Each pair's change is taken at the designated pixel and size
    (:func:`pipeline.measurement.image.pair_change`), and its translation is
    that of the flange point at the target, the pin estimate ``p_pin`` (step 4):
    ``R_a^T (t_b - t_a) + (R_a^T R_b - I) p_pin``, which is what moves the image
    (a pair within ``pure_translation_rad`` turns the flange by up to 2e-4 rad, 50 um
    at a 0.25 m pin).

    Returns
    -------
    pair_seg : (N,) the segment of each pair (consecutive still captures with good
        detections, a small pure flange translation apart)
    dF : (N, 3) its flange-frame translation of the pin point
    dm : (N, 3) its change of ``(u, v, s_inv)``
    J : (3, 3) the image Jacobian of every pair (:func:`pipeline.measurement.image_jacobian.fit_image_jacobian`)
    """
    pairs: list[tuple[int, np.ndarray, np.ndarray]] = []
    u, v, s = c.u, c.v, c.s
    cand = []  # (segment, a, b): consecutive still, good captures of one segment
    for k, fr in enumerate(seg_frames):
        st = [i for i in fr if c.still[i] and c.good[i]]
        cand += [(k, a, b) for a, b in zip(st[:-1], st[1:], strict=False)]
    at = np.array([(a, b) for _, a, b in cand], dtype=np.int64).reshape(-1, 2)
    angs, ds = relative_poses(c.T[at[:, 0]], c.T[at[:, 1]])
    for j, (k, a, b) in enumerate(cand):
        ang, d = float(angs[j]), ds[j]
        step = float(np.linalg.norm(d))
        if ang < config.pure_translation_rad and config.min_step_m < step < config.max_step_m:
            # the translation of the flange point at the target (the pin estimate)
            d = d + (c.T[a][:3, :3].T @ c.T[b][:3, :3] - np.eye(3)) @ p_pin
            dm = pair_change(
                (u[a], v[a], s[a]), (u[b], v[b], s[b]), des, config.depth_scaled_jacobian
            )
            pairs.append((k, d, dm))
    if not pairs:
        raise BadInput(
            f"{path}: no two still captures differ by a small pure flange translation: "
            "the image Jacobian cannot be estimated"
        )
    dF_all = np.array([p[1] for p in pairs])
    dm_all = np.array([p[2] for p in pairs])
    J_global = fit_image_jacobian(dF_all, dm_all)
    if J_global is None:
        raise BadInput(
            f"{path}: the small flange translations ({len(pairs)} pairs) do not span "
            "three directions: the image Jacobian cannot be estimated"
        )
    return np.array([p[0] for p in pairs], dtype=np.int64), dF_all, dm_all, J_global


def _representatives(
    seg_frames: list[np.ndarray], finals: list[np.ndarray], c: Captures
) -> list[int]:
    """Step 4: per segment, the capture whose pose stands for the touch-up's final pose."""
    rep = []
    for fr, b in zip(seg_frames, finals, strict=True):
        pick = [int(i) for i in b if c.found[i]] or [
            int(i) for i in fr if c.still[i] and c.found[i]
        ]
        pick = pick or [int(i) for i in fr if c.still[i]] or [int(i) for i in fr]
        rep.append(pick[-1])
    return rep


def _target_jacobians(
    J_global: np.ndarray,
    pair_seg: np.ndarray,
    dF_all: np.ndarray,
    dm_all: np.ndarray,
    labels: np.ndarray,
    config: TouchupConfig,
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Step 3 per target: the Jacobian the targets share, and those with their own.

    ``config.jacobian == "global"``: the global size row times the median
    target's scale, and a target's own scale kept where significant
    (:func:`size_row_scales`); ``"target"``: a full Jacobian per target with at
    least ``min_pairs_per_target`` pairs, the global one unchanged.
    """
    pair_group = np.asarray(labels)[pair_seg].astype(np.int64)  # target of each pair
    J_target: dict[int, np.ndarray] = {}
    if config.jacobian == "target":
        for g in dict.fromkeys(pair_group.tolist()):  # first-seen order
            members = np.flatnonzero(pair_group == g)
            if len(members) >= config.min_pairs_per_target:
                Jg = fit_image_jacobian(dF_all[members], dm_all[members])
                if Jg is not None and np.all(np.isfinite(Jg)):
                    J_target[g] = Jg
    elif config.jacobian == "global":
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
    return J_global, J_target


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
    c = _captures(frames, detections, info)
    # 1. segments; the designated values; 2. loop starts
    if not c.still.any():
        raise BadInput(f"{info.path}: every capture was taken while the arm moved")
    seg_frames = segments(
        c.T, c.still, rot_split_rad=config.rot_split_rad, trans_split_m=config.trans_split_m
    )
    same = {"same_pose_rad": config.same_pose_rad, "same_pose_m": config.same_pose_m}
    finals = [final_block(fr, c.T, c.still, **same) for fr in seg_frames]
    loop_start = loop_starts(seg_frames, c.T, c.still, **same)
    loops = [
        np.array([i for i in fr if i >= start and c.still[i] and c.good[i]], dtype=np.int64)
        for fr, start in zip(seg_frames, loop_start, strict=True)
    ]
    aim = _loop_aim(loops, c, config)
    des = _designated(meta, inferred, finals, c, config, info.path, aim)
    # 4. targets and the pin estimate (final poses), then 3. the image Jacobian at the pin
    rep = _representatives(seg_frames, finals, c)
    labels, p_pin = group_targets(
        c.T[np.array(rep)],
        radius_m=config.group_radius_m,
        ransac_samples=config.ransac_samples,
        seed=config.seed,
    )
    pair_seg, dF_all, dm_all, J_global = _jacobian_pairs(
        seg_frames, c, config, info.path, des, p_pin
    )
    J_global, J_target = _target_jacobians(J_global, pair_seg, dF_all, dm_all, labels, config)
    # 5. averaged final captures, the tilt bias, then one row per touch-up
    uses, shape, settled = final_shapes(finals, c)
    T_rep = np.array([c.T[uses[k][-1]] if uses[k] else c.T[rep[k]] for k in range(len(finals))])
    bias, tilt_deg, resolved = tilt_bias(shape, T_rep, labels, J_global, des.s0)
    if not config.tilt_correction:
        bias[:] = 0.0
    view_g, axis_l = view_geometry(J_global, des.s0, shape[:, 4])
    tilt = Tilt(bias, tilt_deg, resolved, view_g, axis_l)
    out: list[dict[str, Any]] = []
    for k, fr in enumerate(seg_frames):
        g = int(labels[k])
        J = (J_target[g], "target") if g in J_target else (J_global, "global")
        row = (k, fr, finals[k], shape[k, :3], loop_start[k], g, c, des, J, tilt)
        out.append(touchup_row(*row, config.depth_scaled_jacobian))
    table = pd.DataFrame(out)
    # the image's own anisotropy at convergence, (S3) of pipeline.stages.identify.print_shape
    with np.errstate(invalid="ignore", divide="ignore"):
        table["axis_anisotropy"] = 2.0 * (shape[:, 2] - shape[:, 3]) / (shape[:, 2] + shape[:, 3])
    for col, vals in scatter_columns(pair_scatters(pair_seg, dF_all, len(seg_frames))).items():
        table[col] = vals
    # stable column order: declared first, then extras
    table.attrs["image_jacobian"] = J_global.tolist()
    table.attrs["image_jacobian_per_target"] = {int(g): J.tolist() for g, J in J_target.items()}
    table.attrs["pin_estimate_flange"] = p_pin.tolist()
    table.attrs["designated"] = _designated_attrs(des, aim)
    table.attrs["n_jacobian_pairs"] = len(pair_seg)
    table.attrs["settle"] = settled
    captured = capture_noise(uses, c.u, c.v, c.s, J_global, des.s0)
    pose = pose_noise(dF_all, dm_all, J_global, captured, des.s0)
    table.attrs["capture_noise"] = {**captured, **pose}
    table.attrs["implied_target_diameter_m"] = diameter_from_jacobian(J_global, des.s0)
    return table
