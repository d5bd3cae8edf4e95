"""The camera's response curve: what grey level a pixel shows for a given irradiance.

The spec's contour is the boundary "at the grey level halfway between target
and plate". That is the geometric edge only where grey is proportional to
irradiance. Most cameras encode their output (sRGB, a gamma, a vendor curve):
there the halfway *grey* contour of a blurred edge lies where the blurred
irradiance is some other fraction of the step, and every long axis reads short
(dark target) or long (light target) by the same amount. At vtcal's default
blur that is about -0.4 to -0.8 px of long axis, millimetres of pin depth, and
no residual shows it because every touch-up agrees with it.

vtcal therefore detects on *linearised* grey levels ``E = g^-1(I)``: the
inverse response applied to every pixel of the target's window before the
sub-pixel stage (:func:`pipeline.stages.detect.detector.detect_target`,
``DetectConfig.response``). The response comes from, in order: the command
line (``--response``), the recording's ``touchup`` metadata key
``camera_response``, else it is estimated from the images themselves
(:func:`pipeline.stages.image.response_estimate.estimate_response`).

Curves (``Response.spec``): ``linear``; ``srgb`` (IEC 61966-2-1:
``I = 12.92 E`` below ``E = 0.0031308``, else ``1.055 E^(1/2.4) - 0.055``);
``gamma:G`` (``I = E^(1/G)``, grey normalised to ``[0, 1]``); ``table:I_0,...,I_N``
(any other monotone curve, declared as its encoded values ``I_k = g(k / N)`` at
``N + 1 >= 3`` equally spaced irradiances, in ``[0, 1]`` or in grey levels
``0..255``; ``g^-1`` is its piecewise-linear inverse). Such a curve cannot be
estimated from the edges (below): a camera that uses one must declare it.

The estimate from the images is :mod:`pipeline.stages.image.response_estimate`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pipeline.kinematics.se3 import F64

#: names a response spec may take besides ``gamma:G``
NAMED = ("linear", "srgb")


@dataclass(frozen=True)
class Response:
    """A camera response curve (grey ``I`` in ``[0, 1]`` from irradiance ``E`` in ``[0, 1]``).

    Attributes
    ----------
    kind : ``linear``, ``srgb``, ``gamma`` or ``table``
    gamma : exponent of ``gamma`` (``I = E^(1/gamma)``); 1 otherwise
    table : ``table``'s encoded values ``I_k = g(k / N)``, ``k = 0..N``, in ``[0, 1]``,
        strictly increasing
    """

    kind: str = "linear"
    gamma: float = 1.0
    table: tuple[float, ...] = ()

    @property
    def spec(self) -> str:
        """The text form: ``linear``, ``srgb`` or ``gamma:G``."""
        if self.kind == "gamma":
            return f"gamma:{self.gamma:.4f}"
        if self.kind == "table":
            return "table:" + ",".join(f"{x:.6g}" for x in self.table)
        return self.kind

    @property
    def is_linear(self) -> bool:
        return self.kind == "linear" or (self.kind == "gamma" and self.gamma == 1.0)

    def to_linear(self, grey01: F64) -> F64:
        """Inverse response ``E = g^-1(I)`` of normalised grey ``I`` in ``[0, 1]``."""
        i = np.clip(np.asarray(grey01, dtype=float), 0.0, 1.0)
        if self.kind == "srgb":
            out: F64 = np.where(i <= 0.04045, i / 12.92, ((i + 0.055) / 1.055) ** 2.4)
            return out
        if self.kind == "gamma":
            return np.asarray(i**self.gamma, dtype=float)
        if self.kind == "table":
            t = np.asarray(self.table, dtype=float)
            return np.asarray(np.interp(i, t, np.linspace(0.0, 1.0, len(t))), dtype=float)
        return i

    def slope(self, grey01: F64) -> F64:
        """``dE/dI`` of :meth:`to_linear` (weights the fit's residuals back to grey)."""
        i = np.clip(np.asarray(grey01, dtype=float), 1e-3, 1.0)
        if self.kind == "srgb":
            out: F64 = np.where(
                i <= 0.04045, 1.0 / 12.92, (2.4 / 1.055) * ((i + 0.055) / 1.055) ** 1.4
            )
            return out
        if self.kind == "gamma":
            return np.asarray(self.gamma * i ** (self.gamma - 1.0), dtype=float)
        if self.kind == "table":
            t = np.asarray(self.table, dtype=float)
            dE = 1.0 / (len(t) - 1)
            k = np.clip(np.searchsorted(t, i, side="right") - 1, 0, len(t) - 2)
            return np.asarray(dE / np.maximum(t[k + 1] - t[k], 1e-12), dtype=float)
        return np.ones_like(i)

    def linearise(self, image: np.ndarray) -> np.ndarray:
        """Linearised copy of a grey image in the same grey scale (``float64``).

        ``uint8``: a 256-entry table, values ``255 g^-1(I / 255)``; ``uint16``:
        ``65535 g^-1(I / 65535)``; float images are taken as ``[0, 255]`` grey.
        A linear response returns the image as ``float64`` unchanged.
        """
        img = np.asarray(image)
        if img.dtype == np.uint8:
            return _lut8(self)[img]
        full = 65535.0 if img.dtype == np.uint16 else 255.0
        if self.is_linear:
            return img.astype(np.float64)
        return full * self.to_linear(img.astype(np.float64) / full)


@lru_cache(maxsize=32)
def _lut8(resp: Response) -> np.ndarray:
    lut: np.ndarray = 255.0 * resp.to_linear(np.arange(256, dtype=float) / 255.0)
    lut.setflags(write=False)
    return lut


def parse_response(text: str) -> Response | None:
    """``linear``, ``srgb``, ``gamma:G`` (or ``gamma=G``, ``G``) -> :class:`Response`; ``auto`` -> None.

    Raises
    ------
    ValueError
        Anything else (the caller turns it into a one-line bad-input error).
    """
    t = str(text).strip().lower()
    if t in ("", "auto"):
        return None
    if t.startswith("table:"):
        return _parse_table(text)
    if t in NAMED:
        return Response(t)
    num = t.split(":", 1)[1] if t.startswith("gamma:") else t.split("=", 1)[-1]
    if t.startswith("gamma") or _is_number(num):
        try:
            g = float(num)
        except ValueError:
            g = float("nan")
        if not (math.isfinite(g) and 0.2 <= g <= 5.0):
            raise ValueError(f"camera response {text!r}: gamma must be a number in [0.2, 5]")
        return Response("linear") if g == 1.0 else Response("gamma", g)
    raise ValueError(f"camera response {text!r} is not linear, srgb, gamma:G, table:... or auto")


def _parse_table(text: str) -> Response:
    """``table:I_0,...,I_N`` -> :class:`Response` (values in ``[0, 1]`` or ``0..255``)."""
    try:
        vals = [float(x) for x in text.split(":", 1)[1].replace(";", ",").split(",") if x.strip()]
    except ValueError:
        raise ValueError(
            f"camera response {text[:40]!r}...: table values must be numbers"
        ) from None
    v = np.asarray(vals, dtype=float)
    if len(v) < 3 or not np.all(np.isfinite(v)):
        raise ValueError("camera response table: needs at least 3 finite values")
    if v.max() > 1.0:
        v = v / 255.0
    if not np.all(np.diff(v) > 0) or v[0] < 0 or v[-1] > 1.0 + 1e-9:
        raise ValueError(
            "camera response table: values must increase strictly within [0, 1] (or 0..255)"
        )
    return Response("table", table=tuple(float(x) for x in v))


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
