"""A robust loss for eq. (1)'s least squares that spares its constraint rows.

Eq. (1) itself, its rows, layout and solves: :mod:`pipeline.measurement.pin`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64


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
