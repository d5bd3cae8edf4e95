"""Touch-up extraction, steps 1 and 2: the segments, the final pose, the loop start.

Nothing in a recording marks where a touch-up starts or ends; consecutive still
captures a large move apart belong to different touch-ups (:func:`segments`).
Inside one, the captures at the final pose are the repeated captures at
convergence (:func:`final_block`) and the loop starts where the probing shifts
come back to the first pose (:func:`loop_starts`). The steps are described in
:mod:`pipeline.stages.touchup.stage`; poses are the nominal model's flange poses.
"""

from __future__ import annotations

import numpy as np

from pipeline.kinematics.se3 import rotation_angle


def relative_pose(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, np.ndarray]:
    """Rotation angle and flange-frame translation from pose a to pose b."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    return float(rotation_angle(R)), T_a[:3, :3].T @ (T_b[:3, 3] - T_a[:3, 3])


def segments(
    T: np.ndarray, still: np.ndarray, *, rot_split_rad: float, trans_split_m: float
) -> list[np.ndarray]:
    """Step 1: the frame indices of each touch-up, in order.

    Consecutive still captures whose flange poses differ by more than
    ``rot_split_rad`` in orientation or ``trans_split_m`` in position start a new
    segment, except a pure translation right after a segment's first capture (the
    loop's first step); a capture taken while moving joins the neighbouring still
    capture whose pose is nearer (``0.2 m/rad angle + distance``).

    Parameters
    ----------
    T : (n, 4, 4) flange poses of the captures, in frame order
    still : (n,) the capture was taken standing still (at least one is)
    """
    seg = np.full(len(still), -1, dtype=np.int64)
    still_idx = np.nonzero(still)[0]
    cur = 0
    seg[still_idx[0]] = 0
    n_cur = 1  # still captures in the current segment
    for a, b in zip(still_idx[:-1], still_idx[1:], strict=True):
        ang, d = relative_pose(T[a], T[b])
        # a pure translation after a lone first capture is the loop's first step, however
        # long (a plan made with the nominal robot can start 30+ mm off)
        far = np.linalg.norm(d) > trans_split_m and n_cur > 1
        if ang > rot_split_rad or far:
            cur += 1
            n_cur = 0
        seg[b] = cur
        n_cur += 1
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
    for i in reversed(st[:-1]):
        ang, d = relative_pose(T[last], T[i])
        if ang < same_pose_rad and np.linalg.norm(d) < same_pose_m:
            block.insert(0, i)
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
            for i in st[1:]:
                ang, d = relative_pose(T[st[0]], T[i])
                at_first = ang < same_pose_rad and np.linalg.norm(d) < same_pose_m
                if not at_first:
                    away = True
                elif away:
                    start = i
                    away = False
        loop_start.append(int(start))
    return loop_start
