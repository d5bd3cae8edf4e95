"""Touch-up extraction, steps 1 and 2: the segments, the final pose, the loop start.

Nothing in a recording marks where a touch-up starts or ends; consecutive still
captures a large move apart belong to different touch-ups (:func:`segments`).
Inside one, the captures at the final pose are the repeated captures at
convergence (:func:`final_block`) and the loop starts where the probing shifts
come back to the first pose (:func:`loop_starts`). The steps are described in
:mod:`pipeline.stages.touchups.stage`; poses are the nominal model's flange poses.
"""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.se3 import rotation_angle

#: still captures within this of a touch-up's first are its Jacobian probes (the
#: live loop's are 2 mm shifts, ``measure.loop.LoopConfig.probe_shift_m``; a
#: recorder's may be larger): a translation beyond ``trans_split_m`` from there is
#: still the loop's first step, not a new pose
PROBE_SPAN_M = 0.006


def relative_pose(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle and flange-frame translation from pose a to pose b."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return float(rotation_angle(R)), T_a[:3, :3].T @ (T_b[:3, 3] - T_a[:3, 3])


def relative_poses(T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`relative_pose` of pose pairs ``(n, 4, 4)`` at once: ``(n,)`` angles, ``(n, 3)``
    translations, the same numbers pair by pair (the same products, stacked: no
    per-pair Python and numpy call overhead, which was most of steps 1-3's time)."""
    Rt = T_a[:, :3, :3].transpose(0, 2, 1)
    d = np.matmul(Rt, (T_b[:, :3, 3] - T_a[:, :3, 3])[:, :, None])[:, :, 0]
    return rotation_angle(np.matmul(Rt, T_b[:, :3, :3])), d


def segments(
    T: np.ndarray, still: np.ndarray, *, rot_split_rad: float, trans_split_m: float
) -> list[np.ndarray]:
    """Step 1: the frame indices of each touch-up, in order.

    Consecutive still captures whose flange poses differ by more than
    ``rot_split_rad`` in orientation or ``trans_split_m`` in position start a new
    segment, except a translation while the segment's still captures all lie within
    ``PROBE_SPAN_M`` of its first (the loop's first step, after its first capture or
    the Jacobian probes around it); a capture taken while moving joins the
    neighbouring still capture whose pose is nearer (``0.2 m/rad angle + distance``).

    Parameters
    ----------
    T : (n, 4, 4) flange poses of the captures, in frame order
    still : (n,) the capture was taken standing still (at least one is)
    """
    seg = np.full(len(still), -1, dtype=np.int64)
    still_idx = np.nonzero(still)[0]
    cur = 0
    seg[still_idx[0]] = 0
    first = int(still_idx[0])  # the current segment's first still capture
    span = 0.0  # how far its still captures lie from that first one
    angs, ds = relative_poses(T[still_idx[:-1]], T[still_idx[1:]])
    for k, b in enumerate(still_idx[1:]):
        ang, d = float(angs[k]), ds[k]
        # a translation before the segment has moved beyond its probes is the loop's
        # first step, however long (a plan made with another pin or the nominal robot
        # can start 30+ mm off)
        far = np.linalg.norm(d) > trans_split_m and span > PROBE_SPAN_M
        if ang > rot_split_rad or far:
            cur += 1
            first, span = int(b), 0.0
        else:
            span = max(span, float(np.linalg.norm(T[b][:3, 3] - T[first][:3, 3])))
        seg[b] = cur
    for i in np.nonzero(~still)[0]:
        prev = still_idx[still_idx < i]
        nxt = still_idx[still_idx > i]
        cand = []
        for j in [int(x) for x in prev[-1:]] + [int(x) for x in nxt[:1]]:
            ang, d = relative_pose(T[j], T[i])
            cand.append((ang * 0.2 + np.linalg.norm(d), j))
        seg[i] = seg[min(cand)[1]] if cand else 0
    n_seg = int(seg.max()) + 1
    return [np.nonzero(seg == k)[0] for k in range(n_seg)]


def final_block(
    fr: np.ndarray, T: np.ndarray, still: np.ndarray, *, same_pose_rad: float, same_pose_m: float
) -> np.ndarray:
    """Step 2: the still captures of segment ``fr`` at its final pose, in order.

    The final pose is that of the segment's last still capture; the block is the
    run of still captures before it within ``same_pose_rad`` and ``same_pose_m``
    (empty when the segment has no still capture).
    """
    st = [i for i in fr if still[i]]
    if not st:
        return np.array([], dtype=np.int64)
    last = st[-1]
    block = [last]
    angs, ds = relative_poses(T[[last] * (len(st) - 1)], T[st[:-1]])
    for k in reversed(range(len(st) - 1)):
        if angs[k] < same_pose_rad and np.linalg.norm(ds[k]) < same_pose_m:
            block.insert(0, st[k])
        else:
            break
    return np.array(block, dtype=np.int64)


def loop_starts(
    seg_frames: list[np.ndarray],
    T: np.ndarray,
    still: np.ndarray,
    *,
    same_pose_rad: float,
    same_pose_m: float,
) -> list[int]:
    """Step 2: per segment, the frame the touch-up loop starts at.

    The last still capture that returns to the segment's first pose (within
    ``same_pose_rad`` and ``same_pose_m``) after leaving it, since the probing
    shifts come back to the base pose before the loop; else the segment's
    first capture.
    """
    loop_start = []
    for fr in seg_frames:
        st = [i for i in fr if still[i]]
        start = fr[0]
        if st:
            away = False
            angs, ds = relative_poses(T[[st[0]] * (len(st) - 1)], T[st[1:]])
            for k, i in enumerate(st[1:]):
                at_first = angs[k] < same_pose_rad and np.linalg.norm(ds[k]) < same_pose_m
                if not at_first:
                    away = True
                elif away:
                    start = i
                    away = False
        loop_start.append(int(start))
    return loop_start
