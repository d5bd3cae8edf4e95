"""The pin side of a touch-up: eq. (1) of the method paper, its layout, rows and solves.

    T_base_flange(q_i; x) @ (p_flange_pin + d_i) = p_base_target[k(i)]          (1)

with ``x`` the error model's parameters, ``d_i`` the touch-up's residual correction
(flange frame, :func:`pipeline.measurement.image.residual_correction`) and
``k(i)`` the target it touched. Linearised, touch-up ``i`` gives three rows over
the parameters laid out as :class:`ParamLayout` declares, ``[kinematic | pin | targets]``:

    A_i = B_i [ dp_i/dx  |  R_i  |  -E_k(i) ]                                   (R)

``R_i = R_base_flange(q_i)``, ``E_k`` the three columns of target ``k`` and ``B_i``
the row weighting: ``sqrt(w_i) I``, or ``sqrt(w_i) W R_i^T`` whitened in the flange
frame (:mod:`pipeline.estimation.whitening`). A known distance ``D`` between
targets ``a`` and ``b`` adds the row ``w_D (|t_a - t_b| - D)`` (:func:`distance_row`).

- :class:`Problem`: residuals (1) and their analytic Jacobian, weights,
  whitening, known distances and the scale gauge (identification, cross-validation,
  structural identifiability, the planning Jacobian);
- :func:`rows`: the rows (R) of any subset of touch-ups (outlier rejection's
  mean-shift tests, the planner's candidate information);
- :func:`solve_pin_targets`: the one linear least-squares solve of (1) for the pin
  and targets at fixed kinematics: identification's start
  (:func:`initial_pin_targets`), and with a chain's kinematics
  (:func:`fit_pin_and_targets`) plausibility, validate and the report's nominal fit.

The method and its sources: the module docstring of :mod:`pipeline.stages.identify.stage`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain, fk
from pipeline.kinematics.se3 import F64
from pipeline.measurement.data import FitData
from pipeline.models.base import ErrorModel


@dataclass(frozen=True)
class ParamLayout:
    """The columns of eq. (1)'s Jacobian: ``[kinematic (n_kin) | pin (3) | targets (3K)]``.

    Attributes
    ----------
    n_kin : kinematic columns (all of a model's parameters, or the identified ones)
    n_targets : ``K``, the targets; target ``k`` owns columns ``n_kin + 3 + 3k + (0, 1, 2)``
    """

    n_kin: int
    n_targets: int

    @property
    def n(self) -> int:
        """All columns, ``n_kin + 3 + 3K``."""
        return self.n_kin + 3 + 3 * self.n_targets

    @property
    def n_nuisance(self) -> int:
        """The pin and target columns, ``3 + 3K``."""
        return 3 + 3 * self.n_targets

    @property
    def kin(self) -> slice:
        return slice(0, self.n_kin)

    @property
    def pin(self) -> slice:
        return slice(self.n_kin, self.n_kin + 3)

    def target(self, k: int) -> slice:
        """The three columns of target ``k``."""
        c0 = self.n_kin + 3 + 3 * int(k)
        return slice(c0, c0 + 3)

    def target_start(self, tk: ArrayLike) -> np.ndarray:
        """First column of each row's target, ``n_kin + 3 + 3 tk`` (same shape as ``tk``)."""
        return self.n_kin + 3 + 3 * np.asarray(tk, dtype=np.int64)

    def target_columns(self, ks: ArrayLike) -> np.ndarray:
        """The columns of targets ``ks``, three each, flat (3 len(ks),)."""
        return (self.target_start(ks)[:, None] + np.arange(3)).ravel()


class DistanceWeight(Protocol):
    """What :class:`Problem` reads of a fit's settings (e.g. ``IdentifyConfig``)."""

    distance_weight: float


def rows(
    layout: ParamLayout,
    kin: F64,
    pin: F64,
    tk: ArrayLike,
    target: F64 | None = None,
) -> F64:
    """Rows (R) of touch-ups, ``(N, 3, layout.n)``: ``[kin | pin | -target on k(i)]``.

    Parameters
    ----------
    kin : (N, 3, n_kin) ``B_i dp_i/dx`` (already weighted, scaled or reduced)
    pin : (N, 3, 3) ``B_i R_i``
    tk : (N,) each row's target index in the layout (0..K-1)
    target : the target block ``B_i`` to negate: None for ``I`` (unweighted), an
        ``(N,)`` array ``s_i`` for ``s_i I`` (only the diagonal written), or an
        ``(N, 3, 3)`` array
    """
    t0 = layout.target_start(tk)
    N = len(t0)
    A = np.zeros((N, 3, layout.n))
    A[:, :, layout.kin] = kin
    A[:, :, layout.pin] = pin
    at = np.arange(N)
    if target is None:
        for c in range(3):
            A[at, c, t0 + c] = -1.0
    elif target.ndim == 1:
        for c in range(3):
            A[at, c, t0 + c] = -target
    else:
        for c in range(3):
            A[at[:, None], np.arange(3)[None, :], (t0 + c)[:, None]] = -target[:, :, c]
    return A


def whitened_rows(
    layout: ParamLayout, B: F64, Jx: F64, R: F64, tk: ArrayLike, *, einsum: bool = False
) -> F64:
    """Rows (R) with the row weighting ``B_i`` (N, 3, 3) applied: ``(N, 3, layout.n)``.

    ``Jx`` (N, 3, n_kin), ``R`` (N, 3, 3). ``einsum`` forms ``B_i X_i`` with
    :func:`numpy.einsum` instead of ``@`` (BLAS): the same product summed in
    another order. Outlier rejection's tests were built with it; kept so their
    p-values stay bit for bit what they were (``bench_artefacts_identity``).
    """
    if einsum:
        kin = np.einsum("nab,nbk->nak", B, Jx)
        pin = np.einsum("nab,nbk->nak", B, R)
    else:
        kin, pin = B @ Jx, B @ R
    return rows(layout, kin, pin, tk, B)


def distance_row(
    layout: ParamLayout, t_a: F64, t_b: F64, a: int, b: int, metres: float, weight: float
) -> tuple[F64, float]:
    """The known-distance row of (1) and its residual, ``w_D (|t_a - t_b| - D)``.

    Parameters
    ----------
    t_a, t_b : (3,) the targets' positions ; a, b : their indices in ``layout``
    metres : the known distance ``D`` ; weight : ``w_D``

    Returns
    -------
    row : (layout.n,) ``+w_D u`` on target ``a``, ``-w_D u`` on ``b``, ``u`` the unit
        vector from ``b`` to ``a`` ; residual : float
    """
    u = t_a - t_b
    n = float(np.linalg.norm(u))
    u = u / max(n, 1e-12)
    row = np.zeros(layout.n)
    row[layout.target(a)] = weight * u
    row[layout.target(b)] = -weight * u
    return row, weight * (n - metres)


def solve_pin_targets(
    R: F64, p0: F64, tk: ArrayLike, K: int, sw: ArrayLike | None = None
) -> tuple[F64, F64, F64]:
    """The pin and targets that best explain touch-ups at FIXED kinematics (linear (1)).

    With ``p0_i = T_base_flange(q_i) d_i`` (the point the flange carries at the
    residual correction alone) (1) is linear in the pin ``p`` and the targets ``c``:

        R_i p - c_k(i) = -p0_i    =>    [R_i, -E_k] [p; c] = -p0_i

    solved by least squares with the rows weighted by ``sw``.

    Parameters
    ----------
    R : (N, 3, 3) ``R_base_flange(q_i)`` ; p0 : (N, 3) base frame, m
    tk : (N,) target index 0..K-1 of each row ; K : number of targets
    sw : (N,) row weights (square roots), default 1

    Returns
    -------
    pin : (3,) flange frame ; targets : (K, 3) base frame ;
    residuals : (N, 3) ``R_i p + p0_i - c_k(i)``, base frame (m)
    """
    N = len(R)
    layout = ParamLayout(0, K)
    A = rows(layout, np.zeros((N, 3, 0)), R, tk).reshape(3 * N, layout.n)
    b = -np.asarray(p0, dtype=float).ravel()
    w = np.ones(3 * N) if sw is None else np.repeat(np.asarray(sw, dtype=float), 3)
    sol = np.asarray(np.linalg.lstsq(A * w[:, None], b * w, rcond=None)[0], dtype=np.float64)
    r = (A @ sol - b).reshape(N, 3)
    return sol[:3], sol[3:].reshape(K, 3), r


def fit_pin_and_targets(
    chain: Chain,
    q: ArrayLike,
    d: ArrayLike,
    tk: ArrayLike,
    K: int,
    sw: ArrayLike | None = None,
) -> tuple[F64, F64, F64]:
    """:func:`solve_pin_targets` with the kinematics of ``chain`` (e.g. the nominal robot).

    ``(R_i, t_i) = T_base_flange(q_i)`` of ``chain``, ``p0_i = t_i + R_i d_i``.

    Parameters
    ----------
    chain : the kinematics, base to flange
    q : (N, n) joint vectors ; d : (N, 3) residual corrections, flange frame (m)
    tk : (N,) target index 0..K-1 of each row ; K : number of targets
    sw : (N,) row weights (square roots), default 1

    Returns
    -------
    pin : (3,) flange frame ; targets : (K, 3) base frame ;
    residuals : (N, 3) ``R_i (p + d_i) + t_i - c_{k(i)}``, base frame (m)
    """
    T = fk(chain, np.asarray(q, dtype=float))
    R, t = T[:, :3, :3], T[:, :3, 3]
    p0 = t + np.einsum("nij,nj->ni", R, np.asarray(d, dtype=float))
    return solve_pin_targets(R, p0, tk, K, sw)


def initial_pin_targets(model: ErrorModel, data: FitData, x: F64) -> tuple[F64, F64]:
    """:func:`solve_pin_targets` of ``data`` at the kinematics ``x`` of ``model``."""
    p0, R, _ = model.pin_and_jacobian(x, data.q, data.d, jac=False)
    pin, targets, _ = solve_pin_targets(R, p0, data.tk, data.K, data.sw)
    return pin, targets


class Problem:
    """Residuals (1) and their analytic Jacobian over ``z = [x_free, pin, targets]``."""

    def __init__(
        self,
        model: ErrorModel,
        data: FitData,
        config: DistanceWeight,
        gauge: F64 | None = None,
    ) -> None:
        self.model = model
        self.data = data
        self.P = model.n_params
        self.layout = ParamLayout(self.P, data.K)
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
        """Residual (m,) and Jacobian (m, P + 3 + 3K) over all model parameters.

        Rows: ``sqrt(w_i) (p_i - t_k)`` (3 per touch-up), whitened to
        ``sqrt(w_i) W R_i^T (p_i - t_k)`` when :attr:`W` is set; one
        ``w_D (|t_A - t_B| - D)`` per known distance; ``w_D g . x`` for the gauge.
        Columns: ``d/dx = sqrt(w) [W R^T] dp/dx``, ``d/dp_pin = sqrt(w) [W R^T] R``,
        ``d/dt_k = -sqrt(w) [W R^T]``. Whitened, ``W R_i^T`` is held fixed (Gauss-Newton
        in the rotation): the kinematic columns omit ``W (dR_i^T/dx) (p_i - t_k)``,
        which vanishes with the residual; the pin and target columns are exact
        (``tests/test_estimation.py`` checks both against central differences).
        """
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
        dist_rows = [
            distance_row(self.layout, targets[a], targets[b], a, b, dm, self.wd)
            for a, b, dm in D.dist
        ]
        for j, (_, res) in enumerate(dist_rows):
            r[3 * self.N + j] = res
        if self.gauge is not None:
            r[-1] = self.wd * float(self.gauge @ x)
        if not jac:
            return r, None
        assert Jx is not None
        J = np.zeros((self.m, self.layout.n))
        sw = D.sw[:, None, None]
        if M is None:
            A = rows(self.layout, Jx * sw, R * sw, D.tk, D.sw)
        else:
            A = whitened_rows(self.layout, M * sw, Jx, R, D.tk)
        J[: 3 * self.N] = A.reshape(3 * self.N, self.layout.n)
        for j, (row, _) in enumerate(dist_rows):
            J[3 * self.N + j] = row
        if self.gauge is not None:
            J[-1, : self.P] = self.wd * self.gauge
        return r, J

    def columns(self) -> np.ndarray:
        """Columns of the full Jacobian that ``z`` covers."""
        return np.concatenate([self.free, np.arange(self.P, self.layout.n)])

    def fun(self, z: F64) -> F64:
        # the Jacobian comes almost free with the residual and MINPACK asks for it at
        # the point it just evaluated (accepted steps): compute both, keep the last
        r, J = self.full_eval(*self.split(z))
        assert J is not None
        self._last = (z.tobytes(), J)
        return r

    def set_data(self, data: FitData) -> None:
        """Replace the rows' data (weights, corrections) and forget the cached Jacobian."""
        self.data = data
        self.__dict__.pop("_last", None)

    def jac(self, z: F64) -> F64:
        last = getattr(self, "_last", None)
        if last is not None and last[0] == z.tobytes():
            J = last[1]
        else:
            J = self.full_eval(*self.split(z))[1]
            assert J is not None
        return J[:, self.columns()]
