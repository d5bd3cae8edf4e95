"""Are two error models told apart by their held-out errors? A paired test on the same touch-ups.

Every model is cross-validated on the same folds, so each held-out touch-up ``i``
has an error ``e_a,i`` under model ``a`` and ``e_b,i`` under ``b``. Their squared
errors differ by ``d_i = e_a,i^2 - e_b,i^2``; the touch-ups' own noise is common to
both and cancels in the pairing. Over the ``n`` touch-ups both scored::

    dbar = mean(d_i),   se = sd(d_i) / sqrt(n),   z = dbar / se                   (T1)

Two models whose ``|z|`` is below :data:`Z_APART` (about 95 % two-sided) are *not
told apart*: the choice between them is the data's noise, not their accuracy
(``held-out RMS`` ``sqrt(mean e^2)`` differs by ``dbar / (2 rms)`` to first order).
The run's choice, ``vtcal compare`` and the audit's ranking say so.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

#: |z| of (T1) below this: the two models are not told apart (two-sided 95 %)
Z_APART = 1.96
#: fewer touch-ups scored by both: no test
MIN_PAIRS = 6


def paired_z(errors: pd.DataFrame, a: str, b: str, scheme: str = "kfold") -> tuple[float, int]:
    """(T1) for models ``a`` and ``b``: ``(z, n)``; z > 0 when ``a`` misses more.

    Parameters
    ----------
    errors : cross-validation's held-out table (``model``, ``scheme``, ``touchup_id``,
        ``error_mm``; rows without an error are left out)
    a, b : model names ; scheme : ``kfold`` (the figure the run ships on)

    Returns
    -------
    (z, n): NaN z with fewer than :data:`MIN_PAIRS` common touch-ups or no spread
    """
    e = errors[(errors["scheme"] == scheme) & errors["error_mm"].notna()]
    ea = e[e["model"] == a].set_index("touchup_id")["error_mm"]
    eb = e[e["model"] == b].set_index("touchup_id")["error_mm"]
    common = ea.index.intersection(eb.index)
    n = int(len(common))
    if n < MIN_PAIRS:
        return math.nan, n
    d = ea.loc[common].to_numpy() ** 2 - eb.loc[common].to_numpy() ** 2
    sd = float(np.std(d, ddof=1))
    if not sd > 0:
        return math.nan, n
    return float(np.mean(d) / (sd / math.sqrt(n))), n


def not_told_apart(errors: pd.DataFrame, chosen: str, models: list[str]) -> dict[str, Any]:
    """(T1) of every other model against ``chosen``: ``{model: {"z", "n", "told_apart"}}``.

    ``told_apart`` is None where the test could not be made.
    """
    out: dict[str, Any] = {}
    for m in models:
        if m == chosen:
            continue
        z, n = paired_z(errors, m, chosen)
        out[m] = {
            "z": z,
            "n": n,
            "told_apart": None if not math.isfinite(z) else bool(abs(z) >= Z_APART),
        }
    return out


def sentence(chosen: str, tests: dict[str, Any]) -> str:
    """'' or "; not told apart from it by held-out error: full (z = 0.4), ..."."""
    same = [f"{m} (z = {t['z']:+.1f})" for m, t in tests.items() if t["told_apart"] is False]
    if not same:
        return ""
    return (
        f"; not told apart from {chosen} by held-out error (paired over the same touch-ups, "
        f"|z| < {Z_APART:g}): " + ", ".join(same)
    )
