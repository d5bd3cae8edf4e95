"""Numbers as the HTML pages show them to people (report, audit, compare, validate).

One helper, :func:`fmt`, for every figure a page prints, so that no page shows a raw
float (``40210926531.0``, ``1e-05``, ``0.30000000000000004``): in the everyday range a
fixed number of decimals (tables line up), outside it three significant figures in
scientific notation with a plain exponent (``4.02e10``, ``1.2e-5``). Standard library
only: ``vtcal validate`` renders its page without numpy or pandas.
"""

from __future__ import annotations

import math
from typing import Any

#: figures at or beyond this size are written in scientific notation
LARGE = 1e5
#: non-zero figures below this size are written in scientific notation
SMALL = 1e-3
#: what a missing or non-finite figure shows
MISSING = "–"


def sci(f: float, sig: int = 3) -> str:
    """``f`` in scientific notation with ``sig`` significant figures and a plain exponent:
    ``4.02e10``, ``-1.5e-7`` (not Python's ``4.02e+10``)."""
    mant, _, exp = f"{f:.{max(sig, 1) - 1}e}".partition("e")
    if "." in mant:
        mant = mant.rstrip("0").rstrip(".")
    return f"{mant}e{int(exp)}"


def fmt(x: Any, digits: int = 3) -> str:
    """A figure for a page: ``digits`` decimals between :data:`SMALL` and :data:`LARGE`,
    else :func:`sci` with three significant figures.

    ``None`` and non-finite values are :data:`MISSING`; booleans ``yes``/``no``; text as it
    is; integers as they are below :data:`LARGE`. Accepts numpy scalars (through ``float``).
    """
    if x is None:
        return MISSING
    if isinstance(x, bool) or type(x).__name__ == "bool_":
        return "yes" if x else "no"
    if isinstance(x, str):
        return x
    if isinstance(x, int) or type(x).__name__.startswith(("int", "uint")):
        i = int(x)
        return str(i) if abs(i) < LARGE else sci(float(i))
    try:
        f = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(f):
        return MISSING
    if f != 0 and (abs(f) < SMALL or abs(f) >= LARGE):
        return sci(f)
    return f"{f:.{digits}f}"


def short(x: Any, sig: int = 3) -> str:
    """A setting or a figure without a fixed number of decimals: up to ``sig`` significant
    figures and no trailing zeros (``0.1``, ``0.0586``), :func:`sci` (three) beyond
    :data:`SMALL` and :data:`LARGE` (``2.5e6``); :data:`MISSING` when absent."""
    try:
        f = float(x)
    except (TypeError, ValueError):
        return MISSING if x is None else str(x)
    if not math.isfinite(f):
        return MISSING
    if f != 0 and (abs(f) < SMALL or abs(f) >= LARGE):
        return sci(f)
    return f"{float(f'{f:.{sig}g}'):g}"
