"""One recording's own calibration as the audit uses it: the estimate and its covariance.

Each recording is identified on its own (:func:`pipeline.stages.identify.stage.identify`,
the error model the audit compares with, ``full`` by default). What the change
test needs of it is the vector of estimated quantities

    z = [identified kinematic corrections, pin (3), target centres (3K)]

and its joint covariance. The parameters artefact carries the kinematic and pin
block only (standard errors and correlation rows); a moved base shows in the
targets alone, so the covariance is rebuilt here over all of ``z`` from the
fit's Jacobian at its solution (paper eq. 1 linearised, the identification's
own columns)::

    J = [W R_i^T [J_x, R_i, -E_k] ; w_D / s known-distance rows ; w_D / s gauge row],
    C_z = (J^T J)^-1                                                         (F1)

with ``W = S^(-1/2)`` the touch-up noise in the flange frame estimated from the
fit's residuals (:func:`flange_noise`: a touch-up is less precise along the
camera's view than across it; on image-level recordings the view axis's sigma is
2-6 times the others'), ``s`` its mean sigma and ``w_D`` the fit's constraint
weight on rows in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.audit.identity import AuditItem
from pipeline.kinematics.se3 import F64
from pipeline.stages.identify.types import IdentifyConfig, IdentifyResult

#: the touch-up noise is whitened in the flange frame only when its variances differ this much
ISOTROPIC_BELOW = 4.0
#: the error model the change test compares (every physical cause is one of its columns)
CHANGE_MODEL = "full"


@dataclass
class Estimate:
    """A recording's calibration, as compared.

    Attributes
    ----------
    names : E estimated quantity names (kinematic, ``pin.x/y/z``, ``target.LABEL.x/y/z``)
    z : (E,) values (m, rad) ; cov : (E, E) (F1)
    targets : DataFrame ``target_label, x, y, z, std_x, std_y, std_z`` (m)
    result : the identification result (chain, pin, model, parameters)
    q : (N, n) the usable touch-ups' joint vectors ; tk : (N,) their target index
    labels : K target labels (text) of ``tk``
    gauge : (P,) the scale gauge row ``g . x = 0`` the fit held (no known distance), else None
    dof : the fit's residual degrees of freedom, on which ``cov``'s variance factor was
        estimated (0: unknown; :mod:`pipeline.audit.change` (C3))
    """

    names: list[str]
    z: F64
    cov: F64
    targets: pd.DataFrame
    result: IdentifyResult
    q: F64
    tk: np.ndarray
    labels: list[str]
    gauge: F64 | None = None
    dof: int = 0

    def index(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.names)}


def estimate_of(
    result: IdentifyResult,
    q: F64,
    tk: np.ndarray,
    labels: list[str],
    distances: list[tuple[Any, Any, float]],
    gauge: F64 | None,
    d: F64 | None = None,
) -> Estimate:
    """``z`` and (F1) of one fit (``q``, ``tk``, ``labels``: the touch-ups it used, ``d``
    (N, 3) their residual corrections, zero when None)."""
    p = result.parameters
    est = p[p["estimated_index"] >= 0].sort_values("estimated_index")
    names = est["name"].tolist()
    z = est["value"].to_numpy(dtype=float)
    t = result.targets
    tg = t[["target_label", "x", "y", "z", "std_x", "std_y", "std_z"]].copy()
    tg["target_label"] = tg["target_label"].astype(str)
    pos = tg.set_index("target_label").loc[labels, ["x", "y", "z"]].to_numpy(float)
    names += [f"target.{lab}.{c}" for lab in labels for c in "xyz"]
    z = np.concatenate([z, pos.ravel()])
    e = Estimate(
        names, z, np.zeros((0, 0)), tg.reset_index(drop=True), result, q, tk, labels, gauge
    )
    own = fit_covariance(result, e.names)
    if own is None:  # a fit that made no covariance of its own (prediction only)
        own = covariance(e, distances, np.zeros((len(q), 3)) if d is None else np.asarray(d))
    else:  # identification's covariance: its variance factor on the fit's residual dof
        e.dof = int(result.summary.get("dof") or 0)
    e.cov = own
    return e


def fit_covariance(result: IdentifyResult, names: list[str]) -> F64 | None:
    """The identification's own covariance (:attr:`IdentifyResult.covariance`, the one home
    of ``sigma^2 (J^T J)^-1``) over ``names``; None when it lacks one of them.

    Measured on the foreign pair's touch-ups with Gaussian errors of their own covariance
    (40 draws): its standard errors match the draws' scatter (0.9-1.1x), where (F1)'s
    were 0.3x, which made the change test alarm on every re-recording (chi2 twice its
    degrees of freedom)."""
    if result.covariance is None:
        return None
    at = {n: i for i, n in enumerate(result.covariance_names)}
    if not all(n in at for n in names):
        return None
    j = [at[n] for n in names]
    cov = np.asarray(result.covariance, dtype=float)[np.ix_(j, j)]
    return np.asarray(0.5 * (cov + cov.T))


def point_columns(est: Estimate, names: list[str]) -> F64:
    """``d(touch-up point)/d(quantity)`` (3N, len(names)) at ``est``'s fit, quantities by name
    (kinematic columns of the full parameter vector, ``pin.*``, ``target.LABEL.*``)."""
    res = est.result
    model = res.error_model
    assert model is not None
    _, R, J = model.pin_and_jacobian(res.x, est.q, res.p_flange_pin)
    assert J is not None
    N = len(est.q)
    idx = {n: i for i, n in enumerate(model.param_names)}
    kof = {lab: k for k, lab in enumerate(est.labels)}
    cols = []
    for n in names:
        if n.startswith("pin."):
            cols.append(R[:, :, "xyz".index(n[-1])].reshape(3 * N))
        elif n.startswith("target."):
            lab, ax = n[len("target.") : -2], "xyz".index(n[-1])
            col = np.zeros((N, 3))
            col[est.tk == kof[lab], ax] = -1.0
            cols.append(col.reshape(3 * N))
        else:
            cols.append(J[:, :, idx[n]].reshape(3 * N))
    return np.stack(cols, axis=1) if cols else np.zeros((3 * N, 0))


def constraint_rows(
    est: Estimate, names: list[str], distances: list[tuple[Any, Any, float]]
) -> F64:
    """The fit's exact constraints on ``names``: known distances ``u . (t_a - t_b)`` and the
    scale gauge ``g . x`` (rows, (m, len(names)))."""
    rows = []
    at = {n: i for i, n in enumerate(names)}
    pos = {lab: est.z[at[f"target.{lab}.x"] : at[f"target.{lab}.x"] + 3] for lab in est.labels}
    for a, b, _m in distances:
        sa, sb = str(a), str(b)
        if sa in pos and sb in pos:
            u = pos[sa] - pos[sb]
            u = u / np.linalg.norm(u)
            row = np.zeros(len(names))
            for c in range(3):
                row[at[f"target.{sa}.{'xyz'[c]}"]] = u[c]
                row[at[f"target.{sb}.{'xyz'[c]}"]] = -u[c]
            rows.append(row)
    if est.gauge is not None:
        model = est.result.error_model
        assert model is not None
        gi = {n: i for i, n in enumerate(model.param_names)}
        rows.append(np.array([est.gauge[gi[n]] if n in gi else 0.0 for n in names]))
    return np.array(rows).reshape(len(rows), len(names))


def flange_noise(est: Estimate, d: F64) -> tuple[F64, float] | None:
    """The touch-up noise of the fit in the flange frame: ``(W, s)`` with ``W = S^(-1/2)``,
    ``S = cov(R_i^T (p_i - t_k)) 3N / (3N - E)`` (the fit's residuals, ``p_i`` its pin
    predictions with the corrections ``d`` (N, 3)), eigenvalues floored at 1e-4 of the
    largest, ``s^2`` their mean; None with fewer than 15 residual degrees of freedom.
    Isotropic (``W = I / s``) when the largest variance is below :data:`ISOTROPIC_BELOW`
    times the smallest: a 3x3 covariance from ~70 residual degrees of freedom is
    ``+-30 %`` noise per variance, and whitening by that noise made the change test
    alarm on 2.8 % of comparisons without an event instead of 1 % (bench_audit,
    touch-up histories with isotropic noise; with the rule, the rate in docs/audit.md).
    Image-level recordings are 4.7-32 times more variable along the view."""
    res = est.result
    p = res.predict(est.q, d)
    model = res.error_model
    assert model is not None
    _, R, _ = model.pin_and_jacobian(res.x, est.q, res.p_flange_pin, jac=False)
    at = est.index()
    tg = np.array([est.z[at[f"target.{lab}.x"] : at[f"target.{lab}.x"] + 3] for lab in est.labels])
    e = np.einsum("nji,nj->ni", R, p - tg[est.tk])
    dof = 3 * len(e) - len(est.names)
    if dof < 15:
        return None
    c = e - e.mean(axis=0)
    S = c.T @ c / len(e) * (3 * len(e) / dof)
    lam, V = np.linalg.eigh(S)
    if lam.max() <= 0:
        return None
    lam = np.maximum(lam, lam.max() * 1e-4)
    s = float(np.sqrt(lam.mean()))
    if lam.max() < ISOTROPIC_BELOW * lam.min():  # no anisotropy beyond its estimation noise
        return np.eye(3) / s, s
    return np.asarray((V / np.sqrt(lam)) @ V.T), s


def covariance(est: Estimate, distances: list[tuple[Any, Any, float]], d: F64) -> F64:
    """(F1) over ``est.names``.

    Rows whitened as the fit whitens them, in the flange frame (:func:`flange_noise`:
    ``W R_i^T`` on each touch-up's three rows, unit variance), the constraints as rows of
    the fit's weight relative to them (``IdentifyConfig.distance_weight / s``);
    ``C = (J_w^T J_w)^+``. Without enough residual degrees of freedom: isotropic rows and
    the fit's ``sigma_mm``.
    """
    J = point_columns(est, est.names)
    G = constraint_rows(est, est.names, distances)
    wd = IdentifyConfig().distance_weight
    noise = flange_noise(est, d)
    if noise is not None:
        W, s = noise
        res = est.result
        model = res.error_model
        assert model is not None
        _, R, _ = model.pin_and_jacobian(res.x, est.q, res.p_flange_pin, jac=False)
        N = len(est.q)
        Jw = np.einsum("ab,ncb,ncE->naE", W, R, J.reshape(N, 3, -1)).reshape(3 * N, -1)
        A, sigma = np.vstack([Jw, (wd / s) * G]), 1.0
    else:
        A = np.vstack([J, wd * G])
        sigma = float(est.result.summary.get("sigma_mm", 0.0)) * 1e-3
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    A = A / scale
    inv = np.linalg.pinv(A.T @ A, rcond=1e-12, hermitian=True)
    cov = sigma**2 * inv / np.outer(scale, scale)
    return np.asarray(0.5 * (cov + cov.T))


def fit_table(
    table: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    model: str = CHANGE_MODEL,
    distances: list[tuple[Any, Any, float]] | None = None,
) -> IdentifyResult:
    """One error model fitted on a touch-up table (no cross-validation, no files)."""
    from pipeline.stages.identify.stage import identify

    cfg = IdentifyConfig(model=model, distances=list(distances or []), check_plausibility=False)
    res = identify(table, urdf, base_link, flange_link, cfg)
    assert not isinstance(res, dict)
    return res


def fit_item(item: AuditItem, model: str = CHANGE_MODEL) -> Estimate:
    """The recording's own calibration with ``model`` and its estimate, its covariance
    raised to the recording's measured noise where the fit's residual is below it (F2)."""
    from pipeline.accuracy.validate import usable_touchups

    res = fit_table(item.table, item.urdf, item.base_link, item.flange_link, model, item.distances)
    data = usable_touchups(item.table, list(res.chain.joint_names), item.name)
    gauge = scale_gauge(res, item, bool(item.distances))
    est = estimate_of(res, data.q, data.tk, data.labels, item.distances, gauge, data.d)
    est.cov = est.cov * noise_floor(res.summary, item.noise)
    return est


def noise_floor(summary: dict[str, Any], noise: dict[str, Any] | None) -> float:
    """(F2) the factor a fit's covariance takes where its residual is below the noise the
    recording measured:

        k = max(1, (s_noise / e)^2)                                                    (F2)

    ``e`` one touch-up's own error as the fit's residual estimates it ((V1) of
    :func:`pipeline.accuracy.verdict.own_noise_mm`), ``s_noise`` the touch-up stage's measured
    noise per touch-up (``rms_touchup_um`` of (N4), else the loop steps' whole noise of
    one capture, ``sqrt(tr cov_pose_flange_m2)``). A fit of 30 unknowns on 18 touch-ups
    has 25 residual dof; on image-level recordings of one robot its residual was up to
    6x below the noise the loop measured (3 um against 20 um), its covariance 40x too
    small, and re-recordings alarmed (bench_audit_images --histories 20: 2 of 20; none
    with F2). 1 where either figure is unknown.
    """
    from pipeline.accuracy.verdict import own_noise_mm

    own = own_noise_mm(summary)
    if not noise or own is None or not own > 0:
        return 1.0
    s = noise.get("rms_touchup_um")
    if not (isinstance(s, (int, float)) and np.isfinite(s)):
        cov = np.asarray(noise.get("cov_pose_flange_m2", np.nan), dtype=float)
        s = float(np.sqrt(np.trace(cov)) * 1e6) if cov.shape == (3, 3) else float("nan")
    if not np.isfinite(s):
        return 1.0
    return float(max(1.0, (float(s) * 1e-3 / own) ** 2))


def scale_gauge(res: IdentifyResult, item: AuditItem, has_dist: bool) -> F64 | None:
    """The fit's scale gauge row over the model's parameters (identify's ``_setup``), or None."""
    from pipeline.stages.identify.structure import structure

    model = res.error_model
    assert model is not None
    st = structure(res.model, item.urdf, item.base_link, item.flange_link, has_dist, 1e-8)
    if st.gauge is None:
        return None
    g = np.asarray(st.gauge * model.column_scale(st.length), dtype=float)
    return g / np.linalg.norm(g)


def halves(table: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The touch-ups split in two, alternately within each target (first, third, ... | second, ...)."""
    rank = table.groupby("target_id").cumcount().to_numpy()
    return table[rank % 2 == 0], table[rank % 2 == 1]


def heldout_mm(item: AuditItem, model: str) -> tuple[float, str]:
    """Two-fold held-out consistency of ``model`` on one recording (mm) and a note.

    The touch-ups are split by :func:`halves`; each half's fit is judged on the
    other by :func:`pipeline.accuracy.validate.judge` (its own pin), and the two
    consistencies pooled: ``sqrt((n_a c_a^2 + n_b c_b^2) / (n_a + n_b))``.
    NaN with the reason when a half is too small for the model.
    """
    from pipeline.accuracy.validate import judge, usable_touchups
    from pipeline.errors import VtcalError

    a, b = halves(item.table)
    sq, n = 0.0, 0
    for train, test in ((a, b), (b, a)):
        try:
            res = fit_table(train, item.urdf, item.base_link, item.flange_link, model)
            data = usable_touchups(test, list(res.chain.joint_names), item.name)
            j = judge(model, res.chain, res.p_flange_pin, data, [])
        except VtcalError as exc:
            return float("nan"), f"{model}: {exc}"
        sq += len(data.q) * j["consistency_mm"] ** 2
        n += len(data.q)
    return float(np.sqrt(sq / n)), ""
