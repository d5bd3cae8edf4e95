"""Candidate measuring poses: views of each target solved by nominal inverse kinematics.

For target ``k`` with centre ``c`` and unit plate normal ``n`` a candidate is a
view direction ``w`` (unit, target -> camera) inside a cone of half-angle
``cone`` about ``n`` and a roll ``r`` about ``w``. The camera is taken to look
along the flange ``z`` axis, so the flange orientation is

    R_base_flange = Rot(w, r) @ R0(w),   R0 = [x0, z0 x x0, z0],  z0 = -w

(``x0``: the horizontal direction from the base ``z`` axis to the target,
projected normal to ``w``; the roll is measured from it), and the virtual pin
``p_flange_pin`` sits on the target centre:

    p_base_flange = c - R_base_flange @ p_flange_pin.

Directions spread evenly in solid angle over the cone (sunflower: tilt
``cone sqrt((i + 1/2) / m)``, azimuth stepped by the golden angle; Vogel 1979),
rolls uniform in ``+-roll_range``. Each flange pose is solved by
:func:`pipeline.plan.ik.solve_ik_batch` from several seeds (candidate ``i``
tries the seeds in a rotated order, so different candidates land on different
arm configurations). A candidate is rejected, with its reason kept, when

* ``out of reach``: the flange origin is farther from the base than the sum of
  the chain's link offsets;
* ``no IK solution``: no seed converged inside the joint limits;
* ``joint limit margin``: a joint within ``limit_margin`` of a limit;
* ``near singularity``: the inverse condition number of the flange Jacobian
  ``[J_v; L J_w]`` (angular rows scaled by the working radius ``L``) is below
  ``min_dexterity`` (Salisbury & Craig 1982).

The ellipse stays clear: the circle is seen at most ``cone`` off its normal, so
its image's axis ratio stays above ``cos(cone)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.kinematics.chain import Chain, fk, jacobian
from pipeline.kinematics.se3 import F64, matrix_from_axis_angle
from pipeline.plan.ik import solve_ik_batch
from pipeline.plan.targets import PlanTargets

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
REASONS = ("out of reach", "no IK solution", "joint limit margin", "near singularity")


@dataclass(frozen=True)
class CandidateConfig:
    """Settings of candidate generation (see module docstring).

    Attributes
    ----------
    n_candidates : total candidate views over all targets (split evenly)
    cone_rad : largest angle between the view direction and the plate normal
    roll_rad : rolls about the view axis drawn in ``+-roll_rad``
    p_flange_pin : (3,) the virtual pin in the flange frame (approximate), m
    n_seeds : IK seeds per candidate
    limit_margin_rad : required distance from every joint limit
    min_dexterity : smallest accepted inverse condition number of ``[J_v; L J_w]``
    seed : random seed (rolls, azimuth phase, IK seeds)
    """

    n_candidates: int = 2000
    cone_rad: float = float(np.deg2rad(35.0))
    roll_rad: float = float(np.pi)
    p_flange_pin: tuple[float, float, float] = (0.0, 0.0, 0.2)
    n_seeds: int = 6
    limit_margin_rad: float = float(np.deg2rad(2.0))
    min_dexterity: float = 0.02
    seed: int = 0


@dataclass
class CandidateSet:
    """Every candidate, accepted or not.

    Attributes
    ----------
    table : one row per candidate: ``candidate_id, target_id, target_index,
        view_x, view_y, view_z, tilt_rad, roll_rad, accepted, reason,
        dexterity`` and one column per joint (NaN where unsolved)
    q : (C, n) joint vectors of the accepted candidates (``table[accepted]`` order)
    target_index : (C,) index into the targets of each accepted candidate
    counts : ``{target_id: {"candidates": m, "accepted": a, reason: count, ...}}``
    joint_names : chain joint order of ``q``
    """

    table: pd.DataFrame
    q: F64
    target_index: np.ndarray
    counts: dict[int, dict[str, int]]
    joint_names: list[str]

    @property
    def accepted(self) -> pd.DataFrame:
        return self.table[self.table["accepted"]].reset_index(drop=True)


def chain_reach(chain: Chain) -> float:
    """Upper bound of the flange origin's distance from the base: sum of link offsets."""
    return float(sum(np.linalg.norm(j.T_parent_joint[:3, 3]) for j in chain.joints))


def working_radius(centres: F64) -> float:
    """Characteristic length ``L`` (m): RMS distance of the targets from the base, >= 0.1."""
    return float(max(np.sqrt(np.mean(np.sum(np.asarray(centres) ** 2, axis=1))), 0.1))


def view_frames(centre: F64, normal: F64, tilt: F64, azimuth: F64, roll: F64) -> tuple[F64, F64]:
    """View directions and flange orientations of one target's candidates.

    Parameters
    ----------
    centre, normal : (3,) target centre and unit plate normal, base frame
    tilt, azimuth, roll : (m,) angles of each view (see module docstring)

    Returns
    -------
    w : (m, 3) unit view directions (target -> camera), base frame
    R_base_flange : (m, 3, 3)
    """
    z = normal / np.linalg.norm(normal)
    e1 = np.array([1.0, 0.0, 0.0]) - z[0] * z
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, 1.0, 0.0]) - z[1] * z
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    w = (
        np.cos(tilt)[:, None] * z
        + (np.sin(tilt) * np.cos(azimuth))[:, None] * e1
        + (np.sin(tilt) * np.sin(azimuth))[:, None] * e2
    )
    radial = np.array([centre[0], centre[1], 0.0])
    if np.linalg.norm(radial) < 1e-6:
        radial = np.array([1.0, 0.0, 0.0])
    radial /= np.linalg.norm(radial)
    R = np.empty((len(w), 3, 3))
    for i, wi in enumerate(w):
        zc = -wi
        x0 = radial - (radial @ zc) * zc
        if np.linalg.norm(x0) < 1e-6:
            x0 = np.array([0.0, 0.0, 1.0]) - zc[2] * zc
        x0 /= np.linalg.norm(x0)
        R0 = np.column_stack([x0, np.cross(zc, x0), zc])
        R[i] = matrix_from_axis_angle(wi, roll[i]) @ R0
    return w, R


def dexterity(chain: Chain, q: F64, length: float) -> F64:
    """Inverse condition number of ``[J_v; L J_w]`` at the flange origin, (N,)."""
    if len(q) == 0:
        return np.zeros(0)
    J = jacobian(chain, q)
    J[:, 3:] *= length
    s = np.linalg.svd(J, compute_uv=False)
    return np.asarray(s[:, -1] / np.maximum(s[:, 0], 1e-300))


def ik_seeds(chain: Chain, n_seeds: int, rng: np.random.Generator) -> F64:
    """IK seeds: mid-range (limits clipped to +-pi), zero (clipped), then uniform draws."""
    lo = np.maximum(chain.lower, -np.pi)
    hi = np.minimum(chain.upper, np.pi)
    seeds = [0.5 * (lo + hi), np.clip(np.zeros(chain.n_dof), lo, hi)]
    while len(seeds) < n_seeds:
        seeds.append(rng.uniform(lo, hi))
    return np.array(seeds[: max(n_seeds, 1)])


def generate_candidates(
    chain: Chain, targets: PlanTargets, config: CandidateConfig
) -> CandidateSet:
    """Candidate measuring poses of every target (see module docstring).

    Parameters
    ----------
    chain : nominal chain, base link to flange
    targets : approximate centres and plate normals
    config : CandidateConfig

    Returns
    -------
    CandidateSet
    """
    rng = np.random.default_rng(config.seed)
    K = len(targets)
    m = max(int(np.ceil(config.n_candidates / K)), 1)
    pin = np.asarray(config.p_flange_pin, dtype=float)
    L = working_radius(targets.centres)
    reach = chain_reach(chain)
    names = chain.joint_names

    tk = np.repeat(np.arange(K), m)
    i = np.tile(np.arange(m), K)
    tilt = config.cone_rad * np.sqrt((i + 0.5) / m)
    phase = rng.uniform(0.0, 2 * np.pi, K)
    azimuth = phase[tk] + i * GOLDEN_ANGLE
    roll = rng.uniform(-config.roll_rad, config.roll_rad, K * m)
    W = np.empty((K * m, 3))
    T_goal = np.tile(np.eye(4), (K * m, 1, 1))
    for k in range(K):
        sl = slice(k * m, (k + 1) * m)
        w, R = view_frames(targets.centres[k], targets.normals[k], tilt[sl], azimuth[sl], roll[sl])
        W[sl] = w
        T_goal[sl, :3, :3] = R
        T_goal[sl, :3, 3] = targets.centres[k] - R @ pin
    C = K * m
    reason = np.array([""] * C, dtype=object)
    far = np.linalg.norm(T_goal[:, :3, 3], axis=1) > reach
    reason[far] = REASONS[0]

    q, solved = _solve_views(chain, T_goal, far, ik_seeds(chain, config.n_seeds, rng))
    reason[~solved & ~far] = REASONS[1]
    dex = _screen(chain, q, solved, targets.centres[tk], L, config, reason)
    accepted = reason == ""

    table = pd.DataFrame(
        {
            "candidate_id": np.arange(C, dtype=np.int64),
            "target_id": targets.ids[tk],
            "target_index": tk.astype(np.int64),
            "view_x": W[:, 0],
            "view_y": W[:, 1],
            "view_z": W[:, 2],
            "tilt_rad": tilt,
            "roll_rad": roll,
            "accepted": accepted,
            "reason": reason.astype(str),
            "dexterity": dex,
        }
    )
    for c, name in enumerate(names):
        table[name] = q[:, c]
    counts: dict[int, dict[str, int]] = {}
    for k in range(K):
        rk = reason[tk == k]
        counts[int(targets.ids[k])] = {
            "candidates": int(rk.size),
            "accepted": int(np.sum(rk == "")),
            **{r: int(np.sum(rk == r)) for r in REASONS},
        }
    return CandidateSet(
        table=table,
        q=q[accepted],
        target_index=tk[accepted],
        counts=counts,
        joint_names=names,
    )


def _solve_views(chain: Chain, T_goal: F64, far: np.ndarray, seeds: F64) -> tuple[F64, np.ndarray]:
    """Nominal IK of every flange pose ``T_goal`` (C, 4, 4) not ``far``: candidate ``i`` tries
    the seeds from ``i mod S`` on; returns joints ``(C, n)`` (NaN unsolved) and solved."""
    C, S = len(T_goal), len(seeds)
    q = np.full((C, chain.n_dof), np.nan)
    solved = np.zeros(C, dtype=bool)
    for j in range(S):
        todo = np.flatnonzero(~solved & ~far)
        if todo.size == 0:
            break
        qs, ok = solve_ik_batch(chain, T_goal[todo], seeds[(todo + j) % S])
        q[todo[ok]] = qs[ok]
        solved[todo[ok]] = True
    return q, solved


def _screen(
    chain: Chain,
    q: F64,
    solved: np.ndarray,
    centres: F64,
    L: float,
    config: CandidateConfig,
    reason: np.ndarray,
) -> F64:
    """Reject solved candidates near a joint limit or a singularity, or whose pin misses its
    target centre (``centres`` (C, 3)) on the nominal robot: their ``reason`` is set in place.
    Returns the dexterity of every candidate (NaN unsolved)."""
    dex = np.full(len(q), np.nan)
    if solved.any():
        qs = q[solved]
        pin = np.asarray(config.p_flange_pin, dtype=float)
        margin = np.minimum(qs - chain.lower, chain.upper - qs).min(axis=1)
        d = dexterity(chain, qs, L)
        dex[solved] = d
        idx = np.flatnonzero(solved)
        reason[idx[margin < config.limit_margin_rad]] = REASONS[2]
        sing = (d < config.min_dexterity) & (margin >= config.limit_margin_rad)
        reason[idx[sing]] = REASONS[3]
        # sanity: the pin lands on the target (nominal robot)
        T = fk(chain, qs)
        miss = np.linalg.norm(T[:, :3, :3] @ pin + T[:, :3, 3] - centres[idx], axis=1)
        reason[idx[miss > 1e-6]] = REASONS[1]
    return dex
