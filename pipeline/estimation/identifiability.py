"""Which columns of eq. (1) a fit can identify: pivoted QR (Businger & Golub 1965).

Structural redundancies are found on exact synthetic touch-ups of the nominal
robot (:func:`pipeline.stages.identify.structure.structure`, cached per robot and
model); what the actual touch-ups fail to excite by a second pivoted QR
(:func:`select_columns`); each held column gets a reason (:func:`held_reasons`). The method: the module
docstring of :mod:`pipeline.stages.identify.stage` (base-parameter method of Gautier
& Khalil 1990, Hollerbach & Wampler 1996).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from pipeline.kinematics.se3 import F64


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
