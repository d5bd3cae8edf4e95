"""The identification problem of :mod:`pipeline.stages.identify`: eq. (1), its Jacobian,
weights, whitening and the identifiability of its columns.

See the module docstring of :mod:`pipeline.stages.identify` for the measurement
model, the scaling, the pivoted-QR identifiability analysis and the uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd
import scipy.linalg

from pipeline.errors import BadInput, CalibrationFailed
from pipeline.kinematics.chain import load_chain
from pipeline.kinematics.se3 import F64
from pipeline.models import make_model
from pipeline.models.base import ErrorModel
from pipeline.models.observability import project_out
from pipeline.stages.identify_data import FitData, prepare_data
from pipeline.stages.identify_types import DEFAULT_MODEL, IdentifyConfig


class Problem:
    """Residuals (1) and their analytic Jacobian over ``z = [x_free, pin, targets]``."""

    def __init__(
        self,
        model: ErrorModel,
        data: FitData,
        config: IdentifyConfig,
        gauge: F64 | None = None,
    ) -> None:
        self.model = model
        self.data = data
        self.P = model.n_params
        self.wd = float(config.distance_weight)
        self.N = len(data.q)
        self.gauge = gauge  # (P,) row of the scale-gauge constraint gauge @ x = 0, or None
        self.m = 3 * self.N + len(data.dist) + (gauge is not None)
        self.free = np.arange(self.P)
        # (3, 3) whitening of the pin residual in the flange frame, or None (isotropic)
        self.W: F64 | None = None

    # z layout helpers
    def split(self, z: F64) -> tuple[F64, F64, F64]:
        nf = len(self.free)
        x = np.zeros(self.P)
        x[self.free] = z[:nf]
        return x, z[nf : nf + 3], z[nf + 3 :].reshape(self.data.K, 3)

    def join(self, x: F64, pin: F64, targets: F64) -> F64:
        return np.concatenate([x[self.free], pin, targets.ravel()])

    def full_eval(self, x: F64, pin: F64, targets: F64, jac: bool = True) -> tuple[F64, F64 | None]:
        """Residual (m,) and Jacobian (m, P + 3 + 3K) over all model parameters."""
        D = self.data
        pts = pin + D.d
        p, R, Jx = self.model.pin_and_jacobian(x, D.q, pts, jac=jac)
        e = (p - targets[D.tk]) * D.sw[:, None]
        M = None
        if self.W is not None:  # whitened: W R_i^T (p_i - t_k)
            M = np.einsum("ab,ncb->nac", self.W, R)
            e = np.einsum("nab,nb->na", M, e)
        r = np.empty(self.m)
        r[: 3 * self.N] = e.ravel()
        for j, (a, b, dm) in enumerate(D.dist):
            r[3 * self.N + j] = self.wd * (np.linalg.norm(targets[a] - targets[b]) - dm)
        if self.gauge is not None:
            r[-1] = self.wd * float(self.gauge @ x)
        if not jac:
            return r, None
        assert Jx is not None
        ncol = self.P + 3 + 3 * D.K
        J = np.zeros((self.m, ncol))
        sw = D.sw[:, None, None]
        rows = np.arange(3 * self.N).reshape(self.N, 3)
        if M is None:
            J[: 3 * self.N, : self.P] = (Jx * sw).reshape(3 * self.N, self.P)
            J[: 3 * self.N, self.P : self.P + 3] = (R * sw).reshape(3 * self.N, 3)
            for c in range(3):
                J[rows[:, c], self.P + 3 + 3 * D.tk + c] = -D.sw
        else:
            Msw = M * sw
            J[: 3 * self.N, : self.P] = (Msw @ Jx).reshape(3 * self.N, self.P)
            J[: 3 * self.N, self.P : self.P + 3] = (Msw @ R).reshape(3 * self.N, 3)
            for c in range(3):
                J[rows, (self.P + 3 + 3 * D.tk + c)[:, None]] = -Msw[:, :, c]
        for j, (a, b, _) in enumerate(D.dist):
            u = targets[a] - targets[b]
            u = u / max(np.linalg.norm(u), 1e-12)
            J[3 * self.N + j, self.P + 3 + 3 * a : self.P + 6 + 3 * a] = self.wd * u
            J[3 * self.N + j, self.P + 3 + 3 * b : self.P + 6 + 3 * b] = -self.wd * u
        if self.gauge is not None:
            J[-1, : self.P] = self.wd * self.gauge
        return r, J

    def columns(self) -> np.ndarray:
        """Columns of the full Jacobian that ``z`` covers."""
        return np.concatenate([self.free, np.arange(self.P, self.P + 3 + 3 * self.data.K)])

    def fun(self, z: F64) -> F64:
        # the Jacobian comes almost free with the residual and MINPACK asks for it at
        # the point it just evaluated (accepted steps): compute both, keep the last
        r, J = self.full_eval(*self.split(z))
        assert J is not None
        self._last = (z.tobytes(), J)
        return r

    def jac(self, z: F64) -> F64:
        last = getattr(self, "_last", None)
        if last is not None and last[0] == z.tobytes():
            J = last[1]
        else:
            J = self.full_eval(*self.split(z))[1]
            assert J is not None
        return J[:, self.columns()]


def initial_pin_targets(model: ErrorModel, data: FitData, x: F64) -> tuple[F64, F64]:
    """Exact linear least squares of (1) for the pin and targets at fixed kinematics."""
    N, K = len(data.q), data.K
    p0, R, _ = model.pin_and_jacobian(x, data.q, data.d, jac=False)
    A = np.zeros((3 * N, 3 + 3 * K))
    A[:, :3] = R.reshape(3 * N, 3)
    rows = np.arange(3 * N).reshape(N, 3)
    for c in range(3):
        A[rows[:, c], 3 + 3 * data.tk + c] = -1.0
    b = -p0.ravel()
    sw = np.repeat(data.sw, 3)
    sol = np.asarray(np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)[0], dtype=np.float64)
    pin: F64 = sol[:3]
    targets: F64 = sol[3:].reshape(K, 3)
    return pin, targets


@dataclass(frozen=True)
class Structure:
    """What a model can identify from touch-ups of this robot at all."""

    kept: np.ndarray  # columns identified, sorted
    held: dict[int, str]  # column -> reason
    gauge: F64 | None  # (P,) scale-gauge row (scaled units), None if the scale is identified
    length: float  # characteristic length of the scaling the gauge was built in


@lru_cache(maxsize=64)
def structure(
    name: str, urdf: str, base_link: str, flange_link: str, has_dist: bool, tol: float
) -> Structure:
    """Structural identifiability from exact synthetic touch-ups of the nominal robot.

    Redundancies are exact only where the residuals vanish (a base rotation turns
    a residual vector; a uniform scale shrinks it), so they are found on exact
    touch-ups of the nominal robot: 3 targets x 15 poses spread over the joint
    ranges, with a known distance, the Jacobian (scaled, pin and targets
    projected out) through a pivoted QR. Without a known distance one more
    direction is unidentifiable, the uniform scale: the model-parameter
    direction ``v`` that, with the pin and targets, scales every pin position
    (least squares of ``J_x v + J_pin w = p``). It is held by the gauge
    constraint ``v . x_scaled = 0`` (the fit has no component along the scale
    of the nominal robot) instead of holding one arbitrary length. Cached per
    robot and model.
    """
    from pipeline.evaluate import synthetic_touchups

    chain = load_chain(urdf, base_link, flange_link)
    model = make_model(name, chain)
    rng = np.random.default_rng(20240601)
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    p_c = np.array([0.013, -0.009, 0.15])
    # well-spread exact touch-ups: around the zero pose, else around mid-range
    for centre in (np.clip(0.0, lo, hi), 0.5 * (lo + hi)):
        table, tg = synthetic_touchups(
            chain, p_c, 3, 15, rng, q_centre=centre, centre_spread_rad=0.8
        )
        if len(table) >= 36 and table["target_id"].nunique() == 3:
            break
    if len(table) < 12 or table["target_id"].nunique() < 2:
        raise CalibrationFailed(
            f"model {name}: cannot place exact touch-ups on the nominal robot "
            f"{base_link} -> {flange_link} to rate identifiability (joint limits too tight?)"
        )
    data = prepare_data(table, chain, IdentifyConfig(distances=[(0, 1, 1.0)]))
    prob = Problem(model, data, IdentifyConfig(distance_weight=1.0))
    P = model.n_params
    _, J = prob.full_eval(model.zero(), p_c, tg)
    assert J is not None
    Lc = float(np.sqrt(np.mean(np.sum(tg**2, axis=1))))
    pscale = model.column_scale(Lc)
    prio = model.param_priority
    A = project_out(J[:, :P] * pscale, J[:, P:])
    kept, held, _ = select_columns(A * prio, tol)
    reasons = held_reasons(A, kept, held, model.param_names, tol)
    gauge = None
    if not has_dist:
        # scale: the direction that leaves every touch-up row unchanged but stretches the
        # distance between targets 0 and 1 (J_x v + J_pin w + J_t u = 0, d|t0 - t1| = 1)
        N = len(data.q)
        B = np.concatenate([J[:, kept] * pscale[kept], J[:, P:]], axis=1)
        rhs = np.zeros(B.shape[0])
        rhs[3 * N] = 1.0
        sol = np.linalg.lstsq(B, rhs, rcond=None)[0]
        fit = np.linalg.norm(B @ sol - rhs)
        v = sol[: len(kept)]
        if fit < 1e-6 and np.linalg.norm(v) > 0:
            gauge = np.zeros(P)
            gauge[kept] = v / np.linalg.norm(v)
    return Structure(kept=kept, held=reasons, gauge=gauge, length=Lc)


def select_columns(A: F64, tol: float) -> tuple[np.ndarray, np.ndarray, F64]:
    """Pivoted QR of the reduced, scaled Jacobian: kept (sorted) and held columns, |R_ii|."""
    if A.shape[1] == 0:
        return np.arange(0), np.arange(0), np.zeros(0)
    _, R, piv = scipy.linalg.qr(A, mode="economic", pivoting=True)
    rd = np.abs(np.diag(R))
    if rd.size == 0 or rd[0] == 0:
        return np.arange(0), np.asarray(piv), rd
    rank = int(np.sum(rd > tol * rd[0]))
    return np.sort(piv[:rank]), np.asarray(piv[rank:]), rd


def held_reasons(
    A: F64, kept: np.ndarray, held: np.ndarray, names: list[str], tol: float
) -> dict[int, str]:
    """A one-line reason for each held column (see module docstring)."""
    out: dict[int, str] = {}
    norms = np.linalg.norm(A, axis=0)
    big = norms.max() if norms.size else 1.0
    Ak = A[:, kept]
    for j in held:
        j = int(j)
        if norms[j] <= max(tol, 1e-9) * big:
            out[j] = (
                "moves the pin as the target positions or the virtual pin do (base frame, "
                "pin offset): absorbed by them"
            )
            continue
        c = np.linalg.lstsq(Ak, A[:, j], rcond=None)[0] if kept.size else np.zeros(0)
        top = np.argsort(-np.abs(c))[:3]
        deps = ", ".join(names[int(kept[t])] for t in top if abs(c[t]) > 1e-6)
        out[j] = f"redundant with identified parameters ({deps})" if deps else "not identifiable"
    return out


def flange_whitening(prob: Problem, z: F64, n_free: int) -> tuple[F64 | None, F64 | None]:
    """Whitening matrix of the pin residual in the flange frame, from the current fit.

    ``e_i = R_i^T (p_i - t_k)`` over the used rows; ``S = cov(e) m / (m - p)``
    (weighted, centred: a constant flange-frame offset is the pin's). The returned
    ``W = s S^(-1/2)`` (eigenvalues floored at 1e-4 of the largest) keeps residuals
    in metres (``s^2`` is the mean variance). None when the residuals vanish
    (exact data) or fewer than 15 residual degrees of freedom remain.

    Returns
    -------
    W : (3, 3) or None
    sigma : (3,) standard deviations along the principal flange-frame axes, m
    """
    D = prob.data
    x, pin, tg = prob.split(z)
    p, R, _ = prob.model.pin_and_jacobian(x, D.q, pin + D.d, jac=False)
    e = np.einsum("nji,nj->ni", R, p - tg[D.tk])
    w = D.sw**2
    mu = (w[:, None] * e).sum(axis=0) / w.sum()
    c = e - mu
    dof = 3 * len(e) - (n_free + 3 + 3 * D.K)
    if dof < 15:  # a 3x3 covariance from fewer residual degrees of freedom is noise
        return None, None
    S = (w[:, None, None] * c[:, :, None] * c[:, None, :]).sum(axis=0) / w.sum()
    S *= 3 * len(e) / dof
    lam, V = np.linalg.eigh(S)
    if lam.max() < (1e-9) ** 2:  # exact data: nothing to weigh
        return None, None
    lam = np.maximum(lam, lam.max() * 1e-4)
    s = np.sqrt(lam.mean())
    W = s * (V / np.sqrt(lam)) @ V.T
    return W, np.sqrt(lam)


def partial_loss(name: str, n_robust: int) -> Any:
    """A ``least_squares`` loss callable: ``name`` on the first ``n_robust`` residuals
    (the touch-up rows), linear on the rest (known distances, scale gauge), so a
    robust loss never weakens a constraint.

    ``rho(z)`` with ``z = f^2`` (Triggs et al. 2000): soft_l1 ``2(sqrt(1+z)-1)``,
    huber ``z`` or ``2 sqrt(z) - 1``, cauchy ``ln(1+z)``, arctan ``arctan(z)``.
    """
    if name not in ("soft_l1", "huber", "cauchy", "arctan"):
        raise BadInput(f"robust loss {name!r}: use linear, soft_l1, huber, cauchy or arctan")

    def loss(z: F64) -> F64:
        out = np.empty((3, z.size))
        out[0], out[1], out[2] = z, 1.0, 0.0
        a = z[:n_robust]
        if name == "soft_l1":
            t = 1.0 + a
            out[0, :n_robust] = 2.0 * (np.sqrt(t) - 1.0)
            out[1, :n_robust] = t**-0.5
            out[2, :n_robust] = -0.5 * t**-1.5
        elif name == "huber":
            big = a > 1.0
            sa = np.sqrt(np.where(big, a, 1.0))
            out[0, :n_robust] = np.where(big, 2.0 * sa - 1.0, a)
            out[1, :n_robust] = np.where(big, 1.0 / sa, 1.0)
            out[2, :n_robust] = np.where(big, -0.5 / sa**3, 0.0)
        elif name == "cauchy":
            t = 1.0 + a
            out[0, :n_robust] = np.log1p(a)
            out[1, :n_robust] = 1.0 / t
            out[2, :n_robust] = -1.0 / t**2
        else:
            t = 1.0 + a**2
            out[0, :n_robust] = np.arctan(a)
            out[1, :n_robust] = 1.0 / t
            out[2, :n_robust] = -2.0 * a / t**2
        return out

    return loss


def predicted_errors(Jw: F64, cov: F64, p: F64, kind: str) -> F64:
    """Per-pose standard pin error the covariance predicts after a registration.

    The error field ``dp = J_w dz`` (``J_w`` (N, 3, p), ``dz ~ N(0, cov)``) minus its
    best-fit rigid (``absolute``) or similarity (``shape``) motion: to first
    order a projection ``Pr = I - Q Q^T`` onto the complement of the fields
    ``[I, -[p_i]x]`` (and ``p_i - mean`` for a similarity). Returns
    ``sqrt(trace_i(Pr J cov J^T Pr))`` per pose, (N,).
    """
    N = len(p)
    G = Jw.reshape(3 * N, -1)
    if kind != "raw":
        c = p - p.mean(axis=0)
        basis = [np.tile(np.eye(3), (N, 1))]
        rot = np.zeros((N, 3, 3))
        rot[:, 0, 1], rot[:, 0, 2] = c[:, 2], -c[:, 1]
        rot[:, 1, 0], rot[:, 1, 2] = -c[:, 2], c[:, 0]
        rot[:, 2, 0], rot[:, 2, 1] = c[:, 1], -c[:, 0]
        basis.append(rot.reshape(3 * N, 3))
        if kind == "shape":
            basis.append(c.reshape(3 * N, 1))
        Q, _ = np.linalg.qr(np.concatenate(basis, axis=1))
        G = G - Q @ (Q.T @ G)
    var = np.einsum("ij,jk,ik->i", G, cov, G).reshape(N, 3).sum(axis=1)
    return np.asarray(np.sqrt(np.clip(var, 0.0, None)))


def design_jacobian(
    urdf: str,
    base_link: str,
    flange_link: str,
    q: F64,
    target_ids: np.ndarray,
    p_flange_pin: F64,
    *,
    model: str = DEFAULT_MODEL,
    known_distance: bool = False,
) -> tuple[F64, F64, list[str]]:
    """Identification Jacobian of planned touch-ups on the nominal robot (for pose planning).

    Parameters
    ----------
    urdf, base_link, flange_link : the nominal chain
    q : (N, n) planned converged joint vectors
    target_ids : (N,) which target each touches (any labels)
    p_flange_pin : (3,) the (expected) virtual pin
    model : error model whose structurally identifiable parameters are rated
    known_distance : add a distance row between the first two targets

    Returns
    -------
    J_kin : (m, L) scaled columns of the identifiable kinematic parameters
        (radians times the working radius, so every column is in metres)
    J_nuisance : (m, 3 + 3K) pin and target columns
    names : the L parameter names

    ``pipeline.models.observability.observability(J_kin, J_nuisance)`` rates the set.
    """
    chain = load_chain(urdf, base_link, flange_link)
    labels = list(dict.fromkeys(np.asarray(target_ids).tolist()))
    table = pd.DataFrame(np.asarray(q, dtype=float), columns=chain.joint_names)
    table.insert(0, "target_id", [labels.index(t) for t in np.asarray(target_ids).tolist()])
    table.insert(0, "touchup_id", np.arange(len(table)))
    dist: list[tuple[int | str, int | str, float]] = (
        [(0, 1, 1.0)] if known_distance and len(labels) > 1 else []
    )
    data = prepare_data(table, chain, IdentifyConfig(distances=dist))
    m = make_model(model, chain)
    pin = np.asarray(p_flange_pin, dtype=float)
    p, _, _ = m.pin_and_jacobian(m.zero(), data.q, pin, jac=False)
    tg = np.array([p[data.tk == k].mean(axis=0) for k in range(data.K)])
    st = structure(model, urdf, base_link, flange_link, bool(dist), IdentifyConfig().rank_tol)
    Lc = float(max(np.sqrt(np.mean(np.sum(tg**2, axis=1))), 0.1))
    pscale = m.column_scale(Lc)
    prob = Problem(m, data, IdentifyConfig())
    _, J = prob.full_eval(m.zero(), pin, tg)
    assert J is not None
    P = m.n_params
    return J[:, st.kept] * pscale[st.kept], J[:, P:], [m.param_names[int(j)] for j in st.kept]
