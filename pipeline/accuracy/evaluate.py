"""Accuracy the way a laser-tracker check judges it (``spec/outputs.md``).

Over joint vectors spread through the working volume the touch-ups covered,
the virtual-pin positions a model predicts are registered to the true ones and
the remaining distances are the model's error:

* **shape accuracy**: one best-fit similarity (rotation, translation, uniform
  scale) -- what touch-ups alone can deliver;
* **absolute accuracy**: one best-fit rigid motion -- reachable only with a
  known distance (the base frame against the targets is never identifiable,
  hence the registration).

Both registrations are the closed-form least-squares solution of Umeyama
(1991, IEEE PAMI 13(4)), "Least-squares estimation of transformation
parameters between two point patterns", eqs. (40)-(42).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from pipeline.io.run_folder import RUN_FILES
from pipeline.kinematics.chain import Chain, fk
from pipeline.kinematics.se3 import F64


def pin_positions(chain: Chain, p_flange_pin: ArrayLike, q: ArrayLike) -> F64:
    """Virtual-pin positions in the base frame: ``T_base_flange(q) @ p`` -> (N, 3)."""
    T = fk(chain, np.atleast_2d(np.asarray(q, dtype=float)))
    return np.einsum("nij,j->ni", T[:, :3, :3], np.asarray(p_flange_pin, dtype=float)) + T[:, :3, 3]


def register_points(src: ArrayLike, dst: ArrayLike, *, scale: bool) -> tuple[F64, F64, float]:
    """Best-fit ``dst ~ c R src + t`` (Umeyama 1991).

    Parameters
    ----------
    src, dst : (N, 3)
    scale : estimate the uniform scale ``c`` (similarity) or fix ``c = 1`` (rigid)

    Returns
    -------
    R : (3, 3), t : (3,), c : float
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    Sigma = b.T @ a / len(src)
    U, D, Vt = np.linalg.svd(Sigma)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    c = float(np.trace(np.diag(D) @ S) / (a**2).sum(axis=1).mean()) if scale else 1.0
    t = md - c * R @ ms
    return R, t, c


def registered_errors(src: ArrayLike, dst: ArrayLike, *, scale: bool) -> F64:
    """Distances ``|c R src_i + t - dst_i|`` after the best-fit registration, (N,)."""
    R, t, c = register_points(src, dst, scale=scale)
    moved = c * np.asarray(src, dtype=float) @ R.T + t
    return np.asarray(np.linalg.norm(moved - np.asarray(dst, dtype=float), axis=1))


def pin_accuracy(
    chain_model: Chain,
    p_pin_model: ArrayLike,
    chain_true: Chain,
    p_pin_true: ArrayLike,
    q: ArrayLike,
) -> dict[str, float]:
    """Shape and absolute virtual-pin accuracy of a model against the truth.

    Parameters
    ----------
    chain_model, p_pin_model : the model's chain (base to flange) and pin (flange frame)
    chain_true, p_pin_true : the true ones
    q : (N, n) joint vectors spread through the working volume (:func:`workspace_poses`)

    Returns
    -------
    dict
        ``shape_rms_m, shape_max_m`` (similarity registration),
        ``abs_rms_m, abs_max_m`` (rigid registration), ``scale`` (the
        similarity's scale factor, 1 for a perfect length scale).
    """
    pm = pin_positions(chain_model, p_pin_model, q)
    pt = pin_positions(chain_true, p_pin_true, q)
    es = registered_errors(pm, pt, scale=True)
    ea = registered_errors(pm, pt, scale=False)
    _, _, c = register_points(pm, pt, scale=True)
    return {
        "shape_rms_m": float(np.sqrt(np.mean(es**2))),
        "shape_max_m": float(es.max()),
        "abs_rms_m": float(np.sqrt(np.mean(ea**2))),
        "abs_max_m": float(ea.max()),
        "scale": c,
    }


def workspace_poses(q_touchups: ArrayLike, n: int, rng: np.random.Generator) -> F64:
    """Joint vectors spread through the volume the touch-ups covered.

    Each joint is drawn uniformly between the smallest and largest value it
    took over the touch-ups (the joint-space box of the measurements), so the
    pin sweeps the same region and the same orientations as the touch-ups
    without extrapolating beyond any joint's measured range.

    Parameters
    ----------
    q_touchups : (M, n) converged joint vectors
    n : number of poses
    rng : numpy Generator

    Returns
    -------
    (n, n_joints)
    """
    q = np.asarray(q_touchups, dtype=float)
    q = q[np.all(np.isfinite(q), axis=1)]
    lo, hi = q.min(axis=0), q.max(axis=0)
    return np.asarray(lo + (hi - lo) * rng.random((n, q.shape[1])))


# ----------------------------------------------------------------------------- synthetic truth


def perturbed_chain(chain: Chain, deviations: dict[str, dict[str, Any]]) -> Chain:
    """The simulator's true robot: ``origin' = origin(xyz + dxyz) @ RPY(drpy) @ Rot(axis, dq0)``.

    Parameters
    ----------
    chain : nominal chain
    deviations : ``{joint: {"dxyz_m": (3,), "drpy_rad": (3,), "dq0_rad": float}}``
        (the ``deviations`` block of a simulator truth file)
    """
    from pipeline.kinematics.se3 import matrix_from_axis_angle, matrix_from_rpy

    origins = {}
    for j in chain.joints:
        if j.name not in deviations:
            continue
        dv = deviations[j.name]
        T = np.array(j.T_parent_joint, dtype=float)
        T[:3, 3] += np.asarray(dv.get("dxyz_m", (0, 0, 0)), dtype=float)
        R = T[:3, :3] @ matrix_from_rpy(np.asarray(dv.get("drpy_rad", (0, 0, 0)), dtype=float))
        dq0 = float(dv.get("dq0_rad", 0.0))
        if j.type == "prismatic":
            T[:3, :3] = R
            T[:3, 3] += R @ (j.axis * dq0)
        else:
            T[:3, :3] = R @ matrix_from_axis_angle(j.axis, dq0)
        origins[j.name] = T
    return chain.with_origins(origins)


def random_deviations(
    chain: Chain,
    rng: np.random.Generator,
    xyz_m: float = 1e-3,
    rpy_rad: float = 3e-3,
    q0_rad: float = 1.5e-3,
) -> dict[str, dict[str, Any]]:
    """Uniform random deviations of every actuated joint (simulator magnitudes)."""
    return {
        j.name: {
            "dxyz_m": rng.uniform(-xyz_m, xyz_m, 3).tolist(),
            "drpy_rad": rng.uniform(-rpy_rad, rpy_rad, 3).tolist(),
            "dq0_rad": float(rng.uniform(-q0_rad, q0_rad)),
        }
        for j in chain.actuated
    }


def solve_pin_ik(
    chain: Chain,
    p_flange: ArrayLike,
    targets: ArrayLike,
    q_seed: ArrayLike,
    *,
    iters: int = 40,
    tol_m: float = 1e-13,
) -> tuple[F64, np.ndarray]:
    """Joint vectors that put a flange point exactly on targets (batched).

    Minimum-norm Gauss-Newton on the position only, ``q += pinv(J_v) (t - p)``,
    from each seed; the remaining degrees of freedom stay near the seed.

    Parameters
    ----------
    chain : Chain
    p_flange : (3,) point in the flange (tip) frame
    targets : (N, 3) base frame
    q_seed : (N, n)

    Returns
    -------
    q : (N, n)
    ok : (N,) bool, converged to ``tol_m`` and inside the joint limits
    """
    from pipeline.kinematics.chain import jacobian

    pf = np.asarray(p_flange, dtype=float)
    t = np.asarray(targets, dtype=float)
    q = np.array(q_seed, dtype=float)
    for _ in range(iters):
        e = t - pin_positions(chain, pf, q)
        if np.all(np.linalg.norm(e, axis=1) < tol_m):
            break
        Jv = jacobian(chain, q, pf)[:, :3]
        step = np.einsum("nij,nj->ni", np.linalg.pinv(Jv), e)
        q = q + np.clip(step, -0.5, 0.5)
    err = np.linalg.norm(t - pin_positions(chain, pf, q), axis=1)
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.inf)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.inf)
    ok = (err < max(tol_m, 1e-12)) & np.all((q >= lo) & (q <= hi), axis=1)
    return q, ok


def synthetic_touchups(
    chain_true: Chain,
    p_flange_pin: ArrayLike,
    n_targets: int,
    per_target: int,
    rng: np.random.Generator,
    *,
    noise_q_rad: float = 0.0,
    noise_pin_m: float = 0.0,
    noise_flange_m: ArrayLike | None = None,
    spread_rad: float = 0.35,
    q_centre: ArrayLike | None = None,
    centre_spread_rad: float = 0.6,
) -> tuple[pd.DataFrame, F64]:
    """Touch-ups of a known robot: the true pin exactly on each target (plus noise).

    Each target is the true pin position at a random "centre" configuration;
    each of its touch-ups starts from that configuration with every joint moved
    by up to ``spread_rad`` (orientation variety) and is pulled back onto the
    target by minimum-norm Gauss-Newton on the pin position. The pin then
    misses the target by an isotropic normal ``noise_pin_m`` (per axis, base frame)
    plus, if given, a normal miss with per-axis deviations ``noise_flange_m`` (3,)
    in the flange frame (a touch-up is less precise along the camera view), and
    the recorded joints carry normal ``noise_q_rad`` encoder noise; the
    corrections ``d`` are zero.

    Returns
    -------
    table : DataFrame in the touch-up table form (``touchup_id, target_id``,
        one column per joint, ``dx/dy/dz_flange``, ``weight``, ``converged``)
    targets : (n_targets, 3) true target centres, base frame
    """
    pf = np.asarray(p_flange_pin, dtype=float)
    n = chain_true.n_dof
    lo = np.where(np.isfinite(chain_true.lower), chain_true.lower, -np.pi)
    hi = np.where(np.isfinite(chain_true.upper), chain_true.upper, np.pi)
    qc0 = np.zeros(n) if q_centre is None else np.asarray(q_centre, dtype=float)
    rows = []
    targets = np.zeros((n_targets, 3))
    tid = 0
    for k in range(n_targets):
        qc = np.clip(qc0 + rng.uniform(-centre_spread_rad, centre_spread_rad, n), lo, hi)
        targets[k] = pin_positions(chain_true, pf, qc[None])[0]
        got: list[F64] = []
        for _attempt in range(20):
            m = 2 * (per_target - len(got)) + 2
            miss = rng.normal(0.0, noise_pin_m, (m, 3)) if noise_pin_m > 0 else np.zeros((m, 3))
            seeds = qc + rng.uniform(-spread_rad, spread_rad, (m, n))
            q, ok = solve_pin_ik(chain_true, pf, targets[k] + miss, seeds)
            if noise_flange_m is not None:
                # a miss fixed in the flange frame (e.g. depth along the camera view)
                e = rng.normal(0.0, 1.0, (m, 3)) * np.asarray(noise_flange_m, dtype=float)
                Rf = fk(chain_true, q)[:, :3, :3]
                q, ok2 = solve_pin_ik(
                    chain_true, pf, targets[k] + miss + np.einsum("nij,nj->ni", Rf, e), q
                )
                ok &= ok2
            got.extend(q[ok][: per_target - len(got)])
            if len(got) >= per_target:
                break
        for q in got:
            if noise_q_rad > 0:
                q = q + rng.normal(0.0, noise_q_rad, n)
            joints = dict(zip(chain_true.joint_names, q, strict=True))
            rows.append({"touchup_id": tid, "target_id": k, **joints})
            tid += 1
    df = pd.DataFrame(rows)
    for c in ("dx_flange", "dy_flange", "dz_flange"):
        df[c] = 0.0
    df["weight"] = 1.0
    df["converged"] = True
    return df, targets


def judge_run(out: Any, truth: dict[str, Any], n_poses: int, seed: int) -> dict[str, Any]:
    """A finished run folder judged against its simulation truth (``spec/outputs.md``).

    The shipped ``calibrated.urdf`` (to ``virtual_pin``) and the nominal robot with the
    true pin, each against the true robot over ``n_poses`` poses in the volume the
    inlier touch-ups covered (:func:`workspace_poses`, seeded).

    Returns
    -------
    dict: ``after`` / ``before`` (:func:`pin_accuracy` dicts), ``summary`` (identify.json),
    ``best`` (the shipped model's name), ``model_summary`` (its own summary) and
    ``inliers`` (the inliers artefact).
    """
    import json
    from pathlib import Path

    from pipeline.io.artefacts import read_artefact
    from pipeline.kinematics import load_chain

    folder = Path(out)
    summary = json.loads((folder / RUN_FILES["identify"]).read_text())
    base, flange = truth["base_link"], truth["flange_link"]
    calibrated = load_chain(
        (folder / RUN_FILES["calibrated_urdf"]).read_text(), base, "virtual_pin"
    )
    true_chain = load_chain(truth["true_urdf"], base, flange)
    nominal = load_chain(truth["nominal_urdf"], base, flange)
    inl = read_artefact(folder / RUN_FILES["inliers"], "inliers")
    q = workspace_poses(inl[truth["joint_names"]].to_numpy(), n_poses, np.random.default_rng(seed))
    p_true = np.array(truth["p_vt_flange"])
    best = summary["best_model"]
    return {
        "after": pin_accuracy(calibrated, np.zeros(3), true_chain, p_true, q),
        "before": pin_accuracy(nominal, p_true, true_chain, p_true, q),
        "summary": summary,
        "best": best,
        "model_summary": summary.get("models", {}).get(best, summary),
        "inliers": inl,
    }
