"""The designated values a touch-up loop aimed at, read from its own steps.

A recording without ``designated_u`` / ``designated_v`` / ``designated_size_px``
still shows where its loop was going. A visual servo step moves the camera so
that the image measure ``m = (u, v, s)`` changes along its error, by a share
the loop chose (its gain, which may differ per touch-up, or a step-length
limit far from the target)::

    m_{k+1} - m_k = -g_k (m_k - m0),      0 < g_k <= 1                      (D1)

so every step ``k`` lies on the line through ``m_k`` along ``d_k = (m_{k+1} - m_k) / |.|``
and that line passes through the loop's aim ``m0``. The aim is the point nearest
to all the lines (weighted least squares, ``P_k = I - d_k d_k^T`` the projector
across step ``k``)::

    m0 = (sum_k w_k P_k)^-1 sum_k w_k P_k m_k,    w_k = 1 / (|m_{k+1} - m_k|^2 + sigma_m^2)   (D2)

A loop whose Jacobian is off turns its steps a little away from the error, so
a line misses ``m0`` by a share of its distance from it: ``w_k`` trusts the
small steps near the aim most (``sigma_m`` = 0.02 px, a capture's noise, keeps
the last, noise-sized steps from dominating), and a Huber re-weighting drops
the steps that are not servo steps at all. The median of the final captures,
the other estimate, is where the loops *stopped*: a loop stops as soon as its
error is inside the threshold, so the finals sit off ``m0`` on the side the
loops approached from. Measured on the independent writers' recordings with
their declared values removed (tests/test_servo_target.py,
benchmarks/bench_field_variants.py): the conformance sample's finals' median
was 0.09 px (u) and 0.038 px (size) off its declared values, (D2) 0.03 and
0.006 px; the foreign pair's (threshold 0.5 px, three iterations) 0.06-0.13 px
(centre) against 0.002 px, while the size stays 0.006-0.007 px off either
way: that is where the generator's loop aimed in vtcal's measure (its own
detections of the same captures read 0.004-0.006 px larger than vtcal's), a
difference between two detectors no recording shows.

A step is two consecutive poses of one touch-up's loop (still, detected
captures from the loop's start to its final pose, captures at one pose
averaged); the probing moves before the loop are not steps of (D1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.stages.touchups.segments import relative_pose

#: fewest steps (D2) is solved from (each step gives two equations, across it)
MIN_STEPS = 8
#: a capture's noise in ``m`` (px): the floor of a step's length in the weights of (D2)
SIGMA_M_PX = 0.02


@dataclass(frozen=True)
class ServoTarget:
    """What (D1)-(D2) found.

    Attributes
    ----------
    m0 : (3,) the aimed ``(u, v, s)`` (px)
    sd : (3,) its standard error (px), from the fit's residuals
    gain : median over the steps of ``g_k`` (D1), the share of the error a step took
    n_steps : steps used (weight above zero after the re-weighting)
    """

    m0: np.ndarray
    sd: np.ndarray
    gain: float
    n_steps: int


def loop_steps(
    loops: list[np.ndarray], T: np.ndarray, m: np.ndarray, same_pose_rad: float, same_pose_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The steps ``(m_k, m_{k+1} - m_k)`` of every touch-up loop.

    Parameters
    ----------
    loops : per touch-up, the still detected capture indices from the loop's start to
        the end of its final pose, in order
    T : (N, 4, 4) ``T_base_flange`` of every capture
    m : (N, 3) ``(u, v, s)`` of every capture (px)
    same_pose_rad, same_pose_m : two captures closer than both are at one pose

    Returns
    -------
    mk, dm : (K, 3) each
    """
    mk: list[np.ndarray] = []
    dm: list[np.ndarray] = []
    for idx in loops:
        poses: list[list[int]] = []
        for i in idx:
            if poses:
                ang, d = relative_pose(T[poses[-1][-1]], T[i])
                if ang < same_pose_rad and float(np.linalg.norm(d)) < same_pose_m:
                    poses[-1].append(int(i))
                    continue
            poses.append([int(i)])
        means = [m[p].mean(axis=0) for p in poses]
        for a, b in zip(means[:-1], means[1:], strict=True):
            mk.append(a)
            dm.append(b - a)
    if not mk:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.array(mk), np.array(dm)


def servo_target(mk: np.ndarray, dm: np.ndarray, iters: int = 10) -> ServoTarget | None:
    """The loops' aim ``m0`` by (D1)-(D2), or None when the steps cannot tell it.

    Parameters
    ----------
    mk, dm : (K, 3) the steps (:func:`loop_steps`)
    iters : Huber re-weighting passes (threshold 2 robust sigmas of the miss across a step)

    Returns
    -------
    ServoTarget, or None with fewer than :data:`MIN_STEPS` usable steps, lines that do
    not fix a point (condition number of ``sum w P`` above 1e6), or steps that do not
    move towards the point found (median ``g_k`` outside ``(0.05, 1.5]``: not a servo loop).
    """
    keep = np.linalg.norm(dm, axis=1) > 1e-9
    mk, dm = mk[keep], dm[keep]
    K = len(mk)
    if K < MIN_STEPS:
        return None
    L = np.linalg.norm(dm, axis=1)
    d = dm / L[:, None]
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (K, 3, 3)
    w0 = 1.0 / (L * L + SIGMA_M_PX**2)
    h = np.ones(K)
    m0 = np.median(mk + dm, axis=0)
    N = np.eye(3)
    for _ in range(iters):
        w = w0 * h
        N = np.einsum("k,kij->ij", w, P)
        if np.linalg.cond(N) > 1e6:
            return None
        m0 = np.linalg.solve(N, np.einsum("k,kij,kj->i", w, P, mk))
        miss = np.einsum("kij,kj->ki", P, m0 - mk)  # (K, 3) across each step
        z = np.linalg.norm(miss, axis=1) * np.sqrt(w0)  # in units of each step's scale
        scale = 1.4826 * float(np.median(z)) + 1e-12
        h = np.minimum(1.0, 2.0 * scale / np.maximum(z, 1e-12))
    # the share of the error each step took: dm = -g (m - m0) along d
    along = np.einsum("ki,ki->k", m0 - mk, d)
    g = L / np.where(np.abs(along) > 1e-12, along, np.nan)
    gain = float(np.nanmedian(g))
    if not (0.05 < gain <= 1.5):
        return None
    w = w0 * h
    miss = np.einsum("kij,kj->ki", P, m0 - mk)
    s2 = float(np.sum(w * np.sum(miss * miss, axis=1))) / max(2 * K - 3, 1)
    cov = np.linalg.inv(N) * s2
    return ServoTarget(m0=m0, sd=np.sqrt(np.diag(cov)), gain=gain, n_steps=int(np.sum(h > 0.5)))
