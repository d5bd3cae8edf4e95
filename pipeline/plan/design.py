"""The identification Jacobian of candidate poses, reduced to what touch-ups can identify.

One touch-up of target ``k`` at joints ``q_i`` gives the three rows of the
identification problem (eq. 1, :func:`pipeline.measurement.pin.rows`) linearised at
the nominal robot (``x = 0``) with the pin on the target:

    A_i = [ J_x(q_i) D V  |  R_base_flange(q_i)  |  -E_k ]      (3 x (r + 3 + 3K))

``J_x`` from the error model (:meth:`pipeline.models.base.ErrorModel.pin_and_jacobian`),
``D`` the column scaling of identification (radian parameters times the
working radius ``L``, so a radian and the metre it moves the pin weigh alike),
``R`` the pin's columns and ``-E_k`` target ``k``'s. ``V`` (``P x r``) is an
orthonormal basis of the kinematic directions the whole candidate pool
identifies once the pin and targets are estimated alongside: the eigenvectors
of the pool's reduced information ``sum_i (A_x - P_n A_x)^T (...)`` whose
eigenvalues exceed ``1e-10`` of the largest. Directions outside it (the base
frame against the targets, the pin against the last joint, the length scale
without a known distance) no pose set can identify; D-, A- and E-optimality
are invariant to the choice of orthonormal basis, so this removes them
without choosing which named parameter to hold.

The information of a pose set is ``M = sum_i A_i^T A_i`` (additive per pose);
the kinematic part with the nuisance (pin, targets) eliminated is the Schur
complement

    S = M_xx - M_xn M_nn^-1 M_nx                                   (2)

whose eigenvalues are the squared singular values of the projected Jacobian
:func:`pipeline.models.observability.observability` rates (the Schur
complement equals ``A_x^T (I - P_n) A_x``). Adding a pose ``i`` changes (2) by
a rank-3 term (the estimation update with nuisance parameters; e.g. Pukelsheim
1993, ch. 3.11):

    S' = S + At^T (I + H)^-1 At,   At = A_x,i - A_n,i G,   H = A_n,i M_nn^-1 A_n,i^T   (3)

with ``G = M_nn^-1 M_nx``; so one selection step rates every candidate with
3 x 3 algebra.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.chain import Chain
from pipeline.kinematics.se3 import F64
from pipeline.measurement.pin import ParamLayout, rows
from pipeline.models import make_model
from pipeline.models.base import ErrorModel
from pipeline.models.observability import observability

#: ridge added to the nuisance information so targets without poses stay invertible
NUISANCE_RIDGE = 1e-9
#: relative eigenvalue threshold of the pool's reduced information (identifiable directions)
IDENT_TOL = 1e-10


@dataclass
class Design:
    """Candidate rows of the identification Jacobian (see module docstring).

    Attributes
    ----------
    Ax : (C, 3, r) kinematic rows, scaled and reduced to the identifiable basis
    R : (C, 3, 3) pin rows (the flange rotation)
    tk : (C,) target index of each candidate
    K : number of targets
    V : (P, r) identifiable basis in scaled parameter space
    pscale : (P,) column scaling (``L`` for radian parameters, 1 for metres)
    model : the error model (nominal chain)
    p_flange_pin : (3,)
    q : (C, n) candidate joint vectors
    length : working radius ``L``, m
    """

    Ax: F64
    R: F64
    tk: np.ndarray
    K: int
    V: F64
    pscale: F64
    model: ErrorModel
    p_flange_pin: F64
    q: F64
    length: float

    @property
    def r(self) -> int:
        return int(self.Ax.shape[2])

    @property
    def layout(self) -> ParamLayout:
        """Columns of a full row ``A_i``: ``[kinematic (r) | pin | targets]``."""
        return ParamLayout(self.r, self.K)

    @property
    def p(self) -> int:
        """Columns of a full row ``A_i``: ``r + 3 + 3K``."""
        return self.layout.n

    def __len__(self) -> int:
        return len(self.tk)

    # ---------------------------------------------------------------- rows and information

    def rows(self, idx: ArrayLike) -> F64:
        """Full rows ``A_i`` of candidates ``idx``, (B, 3, p) (:func:`pipeline.measurement.pin.rows`)."""
        idx = np.asarray(idx, dtype=np.int64)
        return rows(self.layout, self.Ax[idx], self.R[idx], self.tk[idx])

    def information(self, idx: ArrayLike) -> F64:
        """``M = sum_i A_i^T A_i`` over candidates ``idx``, (p, p)."""
        A = self.rows(idx).reshape(-1, self.p)
        return np.asarray(A.T @ A)

    def schur(self, M: F64) -> F64:
        """Equation (2) for one ``(p, p)`` or a batch ``(B, p, p)`` of informations."""
        r = self.r
        Mnn = M[..., r:, r:] + NUISANCE_RIDGE * np.eye(self.p - r)
        Mxn = M[..., :r, r:]
        G = np.linalg.solve(Mnn, np.swapaxes(Mxn, -1, -2))
        S = M[..., :r, :r] - Mxn @ G
        return np.asarray(0.5 * (S + np.swapaxes(S, -1, -2)))

    def jacobians(self, idx: ArrayLike) -> tuple[F64, F64]:
        """Stacked kinematic and nuisance columns of candidates ``idx``: (3B, r), (3B, 3+3K)."""
        A = self.rows(idx).reshape(-1, self.p)
        return A[:, : self.r], A[:, self.r :]

    def indices(self, idx: ArrayLike) -> dict[str, float]:
        """Observability indices O1..O5 and ``cond`` of a pose set (identification's measure)."""
        Jx, Jn = self.jacobians(idx)
        return observability(Jx, Jn)

    # ---------------------------------------------------------------- prediction

    def kinematic_covariance(self, idx: ArrayLike, sigma_m: float) -> F64:
        """Covariance of ``[y, pin]`` (kinematic coordinates in the basis ``V``, pin), targets
        eliminated: ``sigma^2 (M_ee - M_et M_tt^-1 M_te)^-1`` over the targets that have poses."""
        idx = np.asarray(idx, dtype=np.int64)
        M = self.information(idx)
        e = self.r + 3
        tcols = self.layout.target_columns(np.unique(self.tk[idx]))
        Mee = M[:e, :e]
        Met = M[:e][:, tcols]
        Mtt = M[np.ix_(tcols, tcols)]
        Se = Mee - Met @ np.linalg.solve(Mtt, Met.T)
        return np.asarray(sigma_m**2 * np.linalg.pinv(0.5 * (Se + Se.T), rcond=1e-12))

    def predicted_error(
        self, idx: ArrayLike, sigma_m: float, q_eval: ArrayLike
    ) -> dict[str, float]:
        """Covariance-predicted pin error after calibrating from pose set ``idx``.

        ``dp(q) = [J_x(q) D V, R(q)] de`` with ``de ~ N(0, cov_e)``
        (:meth:`kinematic_covariance`), over the evaluation poses ``q_eval``, after the best
        similarity (shape) or rigid (absolute) registration, exactly as identification
        predicts it (:func:`pipeline.stages.identify.stage.predicted_errors`).

        Returns
        -------
        dict ``shape_rms_m, shape_max_m, absolute_rms_m, absolute_max_m``
        """
        from pipeline.estimation.uncertainty import predicted_errors

        cov = self.kinematic_covariance(idx, sigma_m)
        q_eval = np.asarray(q_eval, dtype=float)
        pw, Rw, Jw = self.model.pin_and_jacobian(self.model.zero(), q_eval, self.p_flange_pin)
        assert Jw is not None
        Jwe = np.concatenate([(Jw * self.pscale) @ self.V, Rw], axis=2)
        out: dict[str, float] = {}
        for kind in ("shape", "absolute"):
            e = predicted_errors(Jwe, cov, pw, kind)
            out[f"{kind}_rms_m"] = float(np.sqrt(np.mean(e**2)))
            out[f"{kind}_max_m"] = float(e.max())
        return out


def build_design(
    chain: Chain,
    model_name: str,
    q: ArrayLike,
    target_index: ArrayLike,
    K: int,
    p_flange_pin: ArrayLike,
    length: float,
) -> Design:
    """Rows of every candidate and the identifiable basis of the pool (module docstring).

    Parameters
    ----------
    chain : nominal chain, base to flange
    model_name : error model (:func:`pipeline.models.get_model`)
    q : (C, n) candidate joint vectors
    target_index : (C,) target of each candidate, 0..K-1
    K : number of targets
    p_flange_pin : (3,) virtual pin, flange frame
    length : working radius ``L`` (m) scaling the radian parameters

    Raises
    ------
    KeyError
        Unknown model name (the CLI turns it into BadInput).
    """
    model = make_model(model_name, chain)
    q = np.asarray(q, dtype=float)
    tk = np.asarray(target_index, dtype=np.int64)
    pin = np.asarray(p_flange_pin, dtype=float)
    _, R, Jx = model.pin_and_jacobian(model.zero(), q, pin)
    assert Jx is not None
    pscale = model.column_scale(length)
    Js = Jx * pscale
    P = model.n_params
    full = Design(
        Ax=Js,
        R=R,
        tk=tk,
        K=K,
        V=np.eye(P),
        pscale=pscale,
        model=model,
        p_flange_pin=pin,
        q=q,
        length=length,
    )
    S = full.schur(full.information(np.arange(len(tk))))
    lam, vec = np.linalg.eigh(S)
    keep = lam > IDENT_TOL * max(float(lam[-1]), 1e-300)
    V = vec[:, keep][:, ::-1]
    full.V = np.ascontiguousarray(V)
    full.Ax = np.ascontiguousarray(Js @ V)
    return full
