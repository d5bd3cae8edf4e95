"""The measurement equation (1) of identification as a least-squares problem.

    T_base_flange(q_i; x) @ (p_flange_pin + d_i) = p_base_target[k]          (1)

:class:`Problem` holds its residual vector and analytic Jacobian (``d/dx`` from
the error model, ``d/dp_pin = R_base_flange``, ``d/dp_target = -I``), the rows'
weights ``sqrt(w_i)``, the flange-frame whitening ``W R_i^T``, the known-distance
rows ``w_D (|p_A - p_B| - D)`` and the scale gauge. Used by identification
(:mod:`pipeline.stages.identify`), pose planning (:mod:`pipeline.estimation.design`) and outlier rejection.
The method and its sources: the module docstring of :mod:`pipeline.stages.identify`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64
from pipeline.models.base import ErrorModel
from pipeline.stages.identify_data import FitData
from pipeline.stages.identify_types import IdentifyConfig


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


def target_positions(targets: pd.DataFrame) -> dict[int, F64]:
    """``{target_id: (3,) fitted position}`` from a targets table."""
    ids = targets["target_id"].to_numpy(dtype=np.int64)
    xyz = targets[["x", "y", "z"]].to_numpy(dtype=float)
    return {int(t): xyz[i] for i, t in enumerate(ids)}
