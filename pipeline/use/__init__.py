"""Using a calibration: predict where the tool goes, compensate targets (public API).

    from pipeline.use import load
    cal = load("runs/cell")                   # the run folder's calibration.json
    pred = cal.forward(q)                     # q (N, n) rad: flange poses, pin, its sigma, region
    sol = cal.inverse(T_base_target, q0)      # joints that reach the targets, residuals

The same as ``vtcal predict`` and ``vtcal compensate`` (``docs/using.md``).
"""

from __future__ import annotations

from pipeline.use.calibration import Calibration, Prediction, load
from pipeline.use.inverse import Solution

__all__ = ["Calibration", "Prediction", "Solution", "load"]
