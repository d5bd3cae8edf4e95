"""Observability indices of an identification Jacobian (pose-set quality measures).

For a scaled identification Jacobian ``J`` (``m`` measurement rows, ``L``
parameter columns, already reduced to identifiable parameters) with singular
values ``s_1 >= ... >= s_L``:

* ``O1 = (s_1 s_2 ... s_L)^(1/L) / sqrt(m)`` -- Borm & Menq (1991): the
  geometric mean, i.e. the volume of the error ellipsoid (D-optimality).
* ``O2 = s_L / s_1`` -- the inverse condition number (Driels & Pathre 1990).
* ``O3 = s_L`` -- the minimum singular value (Nahvi, Hollerbach & Hayward
  1994): the worst-identified direction (E-optimality).
* ``O4 = s_L^2 / s_1`` -- the noise amplification index (Nahvi & Hollerbach
  1996).
* ``O5 = 1 / sum_i (1 / s_i)`` -- Sun & Hollerbach (2008): A-optimality.

Larger is better for all five. ``cond = s_1 / s_L``.
The pose planner and identification both use :func:`observability`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from pipeline.kinematics.se3 import F64


def project_out(J: ArrayLike, J_nuisance: ArrayLike | None) -> F64:
    """Columns of ``J`` with the column space of ``J_nuisance`` removed.

    ``(I - Q Q^T) J`` with ``Q`` an orthonormal basis of ``J_nuisance`` (the
    Schur complement view: what the kinematic parameters tell once nuisance
    unknowns such as target positions and the pin are estimated alongside).
    """
    J = np.asarray(J, dtype=float)
    if J_nuisance is None or np.size(J_nuisance) == 0:
        return J
    U, s, _ = np.linalg.svd(np.asarray(J_nuisance, dtype=float), full_matrices=False)
    Q = U[:, s > s.max() * 1e-12] if s.size else U[:, :0]
    return J - Q @ (Q.T @ J)


def indices_from_singular_values(s: ArrayLike, m: int) -> dict[str, float]:
    """O1..O5 and the condition number from singular values ``s`` (any order)."""
    s = np.sort(np.asarray(s, dtype=float))[::-1]
    if s.size == 0 or s[-1] <= 0:
        nan = float("nan")
        return {"O1": 0.0, "O2": 0.0, "O3": 0.0, "O4": 0.0, "O5": 0.0, "cond": nan}
    return {
        "O1": float(np.exp(np.mean(np.log(s))) / np.sqrt(max(m, 1))),
        "O2": float(s[-1] / s[0]),
        "O3": float(s[-1]),
        "O4": float(s[-1] ** 2 / s[0]),
        "O5": float(1.0 / np.sum(1.0 / s)),
        "cond": float(s[0] / s[-1]),
    }


def observability(J: ArrayLike, J_nuisance: ArrayLike | None = None) -> dict[str, float]:
    """Observability indices O1..O5 and ``cond`` of an identification Jacobian.

    Parameters
    ----------
    J : (m, L) scaled Jacobian of the measurements w.r.t. the identifiable parameters.
    J_nuisance : (m, K), optional
        Columns of unknowns estimated alongside but not rated (targets, pin);
        projected out first (:func:`project_out`).
    """
    A = project_out(J, J_nuisance)
    s = np.linalg.svd(A, compute_uv=False)
    return indices_from_singular_values(s, A.shape[0])
