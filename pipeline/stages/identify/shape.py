"""The print-shape refit of identification: target size and out-of-roundness as extra unknowns.

See :mod:`pipeline.stages.identify.print_shape` for the model and the F-test that decides it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import numpy as np

from pipeline.estimation.distributions import f_sf
from pipeline.estimation.whitening import whitening_params
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.measurement.pin import ParamLayout, Problem
from pipeline.stages.identify.print_shape import ShapeFit
from pipeline.stages.identify.types import IdentifyConfig

#: joint Gauss-Newton steps of the print-shape test without a refit (:func:`_linear_test`)
LINEAR_STEPS = 2
#: joint Gauss-Newton steps (each followed by the full solve) of a print-shape fit
SHAPE_STEPS = 8


def spent_unknowns(
    W: F64 | None, shape: dict[str, Any] | None, components: dict[str, Any] | None = None
) -> int:
    """Unknowns a fit estimated from its residuals outside its Jacobian's columns: the
    flange whitening's shape ((W1) of :mod:`pipeline.estimation.whitening`), a fitted
    print shape's parameters (``shape["n_params"]``, held fixed once fitted) and the
    per-target variance ratios where the targets were weighed apart ((C3) of
    :mod:`pipeline.estimation.components`). All are taken from the residual degrees of
    freedom of the variance factor::

        f = m - p - 5 [whitened] - n_shape [print shape fitted] - (G - 1) [weighed]  (W2)
    """
    n_shape = int(shape.get("n_params") or 0) if shape and shape.get("fitted") else 0
    return whitening_params(W) + n_shape + int((components or {}).get("spent") or 0)


def fit_print_shape(
    prob: Problem, sol: Any, solve: Any, config: IdentifyConfig, n_free: int
) -> tuple[Any, FitData, dict[str, Any], ShapeFit | None]:
    """Each target's print size and out-of-roundness, solved jointly with the fit.

    :mod:`pipeline.stages.identify.print_shape` has the model (S1)-(S2). Three Gauss-Newton
    steps on ``theta`` together with every unknown of ``prob`` (the design ``B`` is
    recomputed from the current kinematics before each), each followed by the full
    solve from where it stood; the rows' corrections become ``d_i + g_i (B_i . theta)``.
    ``auto`` keeps the result when the nested-model F-test on the unwhitened residual
    sums rejects ``theta = 0`` at ``shape_alpha``. Else it tries the relative sizes
    alone (``kappa``, ``K - 1`` parameters: a per-target constant along the view, which
    is also what a per-target error of the image Jacobian's size row leaves after a
    large residual correction) with the same test. Otherwise the fit is the one before.

    Each test is first made without refitting (:func:`_linear_test`: two joint
    Gauss-Newton steps from the fit without print shape, the same F to 1e-3 on the
    tests' cells and to four digits on the standard ones); only a significant one (or
    ``target_shape = "fit"``) is refitted, and the refit's test decides. On the
    standard cells no print shape is significant and identification takes half the
    time it took with every test refitted (docs/speed.md, "The after-ingest goal met").

    Returns
    -------
    sol : the solver result to continue with
    data : the data it belongs to (a copy with the corrected ``d``, or ``prob.data``)
    summary : ``fitted``, ``note``, F-test figures, per-target figures
    shape : the fitted print shape (to correct touch-ups the fit has not seen), or None
    """
    D0 = prob.data
    K = D0.K
    counts = np.bincount(D0.tk, minlength=K)
    if int(counts.min()) < config.shape_min_touchups:
        return (
            sol,
            D0,
            {
                "fitted": False,
                "note": f"print shape not fitted: a target has {int(counts.min())} touch-ups "
                f"(needs {config.shape_min_touchups})",
            },
            None,
        )
    assert D0.shape_g is not None and D0.shape_l is not None
    n_all = 3 * K - 1
    rss0 = _rss(prob, D0, sol.x)
    sol0, W0 = sol, prob.W

    # the whole print model, then the relative sizes alone (K - 1 parameters: a per-target
    # constant along the view, which is also what a per-target error of the image
    # Jacobian's size row leaves after the residual correction); the first significant
    # one is kept (two tests at shape_alpha each)
    tries = [np.arange(n_all)] + ([np.arange(K - 1)] if K > 1 else [])
    tried: list[dict[str, Any]] = []
    start = _Start(prob, D0, W0, sol0, rss0)
    for i, cols in enumerate(tries):
        forced = config.target_shape == "fit" and i == 0
        out, significant = _linear_test(start, cols, config, n_free)
        s1, D1, fitted = sol0, D0, None
        if significant or (forced and "F" in out):
            s1, D1, out, significant, fitted = _attempt(start, cols, solve, config, n_free)
        tried.append(out)
        if significant or (forced and "F" in out):
            out["fitted"] = True
            out["tried"] = [{k: t.get(k) for k in ("parameters", "F", "p_value")} for t in tried]
            return s1, D1, out, fitted
    prob.data, prob.W = D0, W0
    first = tried[0]
    if "F" not in first:
        return sol0, D0, first, None
    return sol0, D0, _not_significant(first, tried, config.shape_alpha), None


def _rss(prob: Problem, D: FitData, z: F64) -> float:
    """Weighted residual sum of squares (m^2) of ``D`` at the fit's unknowns ``z``."""
    x, pin, tg = prob.split(z)
    p, _, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    return float(np.sum(((p - tg[D.tk]) * D.sw[:, None]) ** 2))


def _joint(prob: Problem, D: FitData, cols: np.ndarray, z: F64, theta: F64) -> tuple[F64, F64, F64]:
    """(A, r, B): Jacobian over [z, theta[cols]], residual and the (S2) design at ``z``.

    ``D`` is the data being corrected (its ``shape_g``, ``shape_l``, ``shape_v`` are the
    levers, long axes and anisotropies of :mod:`pipeline.stages.identify.print_shape`);
    the columns of ``theta`` are ``d eps / d theta`` of (S3) at ``theta``.
    """
    from pipeline.stages.identify import print_shape as ps

    assert D.shape_g is not None and D.shape_l is not None
    G, L = D.shape_g, D.shape_l
    K, N, ne = D.K, len(D.q), len(cols)
    x, pin, tg = prob.split(z)
    r, Jf = prob.full_eval(x, pin, tg)
    assert Jf is not None
    _, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    B, _ = ps.design(np.einsum("nij,nj->ni", R, L), D.tk, K, np.einsum("nij,nj->ni", R, G))
    V = np.einsum("nij,nj->ni", R, G) if prob.W is None else G @ prob.W.T
    Bc = ps.print_error(B, D.tk, K, theta, D.shape_v)[1][:, cols]
    S = np.zeros((prob.m, ne))
    S[: 3 * N] = (V[:, :, None] * Bc[:, None, :] * D.sw[:, None, None]).reshape(3 * N, ne)
    return np.hstack([Jf[:, prob.columns()], S]), r, B


class _Start(NamedTuple):
    """Where every print-shape test starts: the problem, its data and whitening, the
    fit without a print shape and its unwhitened residual sum (:func:`_rss`)."""

    prob: Problem
    D0: FitData
    W0: Any
    sol0: Any
    rss0: float


def _linear_test(
    start: _Start, cols: np.ndarray, config: IdentifyConfig, n_free: int
) -> tuple[dict[str, Any], bool]:
    """The F-test of ``theta[cols]`` with the refit replaced by Gauss-Newton steps.

    From the fit without print shape ``z0`` (``sol0``), :data:`LINEAR_STEPS` joint
    Gauss-Newton steps on ``[z, theta[cols]]`` (the design ``B`` and the Jacobian
    recomputed at each point, as :func:`_attempt` has them),

    ``[dz; dtheta] = argmin || r(z, theta) + A(z, theta) [dz; dtheta] ||``,

    and ``rss1`` is the unwhitened residual sum evaluated exactly at the point they
    reach. Near ``z0`` the problem in ``theta`` is linear (the rows' corrections are
    ``d_i + g_i (B_i . theta)``) and ``z0`` is already the minimum for ``theta = 0``,
    so the steps land where the refit does (the F of both, measured on the standard
    cells: docs/speed.md, "The after-ingest goal met"). A significant result (or ``target_shape = "fit"``)
    is refitted by :func:`_attempt` before anything of it is used: the refit's test is
    the one kept.

    Returns
    -------
    summary : as :func:`_attempt`'s (the target figures NaN: not a fit)
    significant : ``p < shape_alpha``
    """
    from pipeline.stages.identify import print_shape as ps

    prob, D0, W0, sol0, rss0 = start
    D, G, n_all, ne, dof1 = _dimensions(D0, cols, n_free)
    if dof1 < 5:
        return {"fitted": False, "note": "print shape not fitted: too few touch-ups"}, False
    # the test is made in (S2), linear in theta, where two steps land; the refit of a
    # significant one (:func:`_attempt`) fits (S3)
    D = dataclasses.replace(D, shape_v=None)
    K = D0.K
    prob.data, prob.W = D, W0
    theta = np.zeros(n_all)
    z = np.array(sol0.x, dtype=float)
    for _ in range(LINEAR_STEPS):
        step, B = _gauss_newton_step(prob, D, cols, z, theta)
        z = z + step[:-ne]
        theta[cols] += step[-ne:]
        D.d[:] = D0.d + G * ps.print_error(B, D.tk, K, theta, D.shape_v)[0][:, None]
    rss1 = _rss(prob, D, z)
    prob.data = D0
    out = _f_test(rss0, rss1, ne, dof1, n_all, config, "tested")
    out["test"] = f"Gauss-Newton ({LINEAR_STEPS} steps from the fit without it)"
    out["targets"] = ps.summarise(theta, np.full(n_all, np.nan), K, config.target_diameter_m)
    return out, out["p_value"] < config.shape_alpha


def _dimensions(D0: FitData, cols: np.ndarray, n_free: int) -> tuple[FitData, F64, int, int, int]:
    """(a copy of ``D0`` the shape's corrections go into, the levers ``G``, the number of
    print parameters ``3K - 1``, the number ``ne`` tested, the degrees of freedom with
    them) of a test of the columns ``cols``; ``n_free`` kinematic unknowns."""
    import dataclasses

    assert D0.shape_g is not None
    K, N, ne = D0.K, len(D0.q), len(cols)
    dof1 = 3 * N + len(D0.dist) - (n_free + ParamLayout(0, K).n_nuisance) - ne
    D = dataclasses.replace(D0, d=D0.d.copy(), d_all=D0.d_all.copy())
    return D, D0.shape_g, 3 * K - 1, ne, dof1


def _gauss_newton_step(
    prob: Problem, D: FitData, cols: np.ndarray, z: F64, theta: F64
) -> tuple[F64, F64]:
    """One joint Gauss-Newton step on ``[z, theta[cols]]`` from ``(z, theta)`` (columns
    scaled to unit norm for the least squares), and the (S2) design ``B`` at ``z``."""
    A, r, B = _joint(prob, D, cols, z, theta)
    cn = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    step = np.linalg.lstsq(A / cn, -r, rcond=None)[0] / cn
    return step, B


def _f_test(
    rss0: float, rss1: float, ne: int, dof1: int, n_all: int, config: IdentifyConfig, verb: str
) -> dict[str, Any]:
    """The nested-model F-test of ``ne`` print-shape parameters on the residual sums
    ``rss0`` (without) and ``rss1`` (with), ``dof1`` degrees of freedom with: the summary
    :func:`_attempt` and :func:`_linear_test` share (their note says ``verb``)."""
    F = ((rss0 - rss1) / ne) / max(rss1 / dof1, 1e-300)
    p_value = f_sf(F, ne, dof1) if rss1 > 0 else 0.0
    what = "print shape" if ne == n_all else "relative print sizes"
    return {
        "fitted": False,
        "parameters": "size and out-of-roundness" if ne == n_all else "size",
        "F": float(F),
        "p_value": p_value,
        "alpha": config.shape_alpha,
        "rss_before_mm2": 1e6 * rss0,
        "rss_after_mm2": 1e6 * rss1,
        "n_params": ne,
        "note": f"{what} {verb} ({ne} parameters, F = {F:.1f}, p = {p_value:.2g})",
    }


def _attempt(
    start: _Start, cols: np.ndarray, solve: Any, config: IdentifyConfig, n_free: int
) -> tuple[Any, FitData, dict[str, Any], bool, ShapeFit | None]:
    """Fit the ``theta`` columns ``cols`` from ``sol0`` on ``D0``; (sol, data, summary,
    significant, the fitted shape)."""
    from pipeline.stages.identify import print_shape as ps

    prob, D0, W0, sol0, rss0 = start

    D, G, n_all, ne, dof1 = _dimensions(D0, cols, n_free)
    if dof1 < 5:
        return (
            sol0,
            D0,
            {"fitted": False, "note": "print shape not fitted: too few touch-ups"},
            False,
            None,
        )
    K = D0.K
    prob.data, prob.W = D, W0
    theta = np.zeros(n_all)
    s1 = sol0
    for _ in range(SHAPE_STEPS):
        step, B = _gauss_newton_step(prob, D, cols, s1.x, theta)
        dz, dth = step[:-ne], step[-ne:]
        # (S3) is not linear in theta: halve a step that raises the residual sum
        rss_old = _rss(prob, D, s1.x)
        trial = theta
        for _h in range(6):
            trial = theta.copy()
            trial[cols] += dth
            D.d[:] = D0.d + G * ps.print_error(B, D.tk, K, trial, D.shape_v)[0][:, None]
            if _rss(prob, D, s1.x + dz) <= rss_old:
                break
            dz, dth = 0.5 * dz, 0.5 * dth
        theta = trial
        D.d_all[D.used_idx] = D.d
        s1 = solve(s1.x)
    A, r, B = _joint(prob, D, cols, s1.x, theta)
    cn = np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    dof_w = prob.m - A.shape[1]
    sig2 = float(r @ r / dof_w) if dof_w > 0 else float("nan")
    _, sv, Vt = np.linalg.svd(A / cn, full_matrices=False)
    good = sv > sv[0] * 1e-12
    cov = (Vt[good].T / sv[good] ** 2) @ Vt[good] * sig2
    std = np.full(n_all, np.nan)
    std[cols] = np.sqrt(np.clip(np.diag(cov)[-ne:], 0, None)) / cn[-ne:]
    rss1 = _rss(prob, D, s1.x)
    out = _f_test(rss0, rss1, ne, dof1, n_all, config, "fitted")
    out["held"] = (
        "the size of target 0's print (the reference): a size error common to every print "
        "moves every touch-up along the view like the virtual pin's own coordinate"
    )
    out["targets"] = ps.summarise(theta, std, K, config.target_diameter_m)
    p_value = out["p_value"]
    if ne < n_all:  # sizes only: the out-of-roundness was not fitted, not zero
        for t in out["targets"]:
            for k in ("ellipticity", "ellipticity_std", "orientation_rad", "out_of_round_um"):
                if k in t:
                    t[k] = float("nan")
    return s1, D, out, p_value < config.shape_alpha, _shape_fit(prob, D, s1.x, theta)


def _shape_fit(prob: Problem, D: FitData, z: F64, theta: F64) -> ShapeFit:
    """The fitted print shape with its plate frames at the fit's kinematics ``z``."""
    from pipeline.stages.identify import print_shape as ps

    assert D.shape_g is not None and D.shape_l is not None
    x, pin, _ = prob.split(z)
    _, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    l_base = np.einsum("nij,nj->ni", R, D.shape_l)
    _, e1, e2 = ps.plate_frames(l_base, D.tk, D.K, np.einsum("nij,nj->ni", R, D.shape_g))
    ids = tuple(int(t) for t in D.target_ids)
    return ShapeFit(theta.copy(), e1, e2, ids, anisotropic=D.shape_v is not None)


def _not_significant(
    first: dict[str, Any], tried: list[dict[str, Any]], alpha: float
) -> dict[str, Any]:
    """The first attempt's summary, saying no attempt was significant (its figures NaN)."""
    first["tried"] = [{k: t.get(k) for k in ("parameters", "F", "p_value")} for t in tried]
    first["note"] = (
        "print shape not significant ("
        + "; ".join(
            f"{t['parameters']}: F = {t['F']:.2f}, p = {t['p_value']:.2g}"
            for t in tried
            if "F" in t
        )
        + f" >= {alpha:g}): perfect circles of one size assumed"
    )
    for t in first["targets"]:
        for k in t:
            if k != "target":
                t[k] = float("nan")
    return first
