"""The correction frame's first fit, made once per process for the same rows and settings.

Every identification in the calibrated correction frame starts with a first fit
(:func:`pipeline.stages.identify.frame.correction_frame`: prediction only, no print
shape, corrections as the table has them). In ``vtcal run`` the outliers stage
identifies its inliers (:func:`pipeline.stages.outliers.stage.flag_outliers`) and the
identify stage then identifies the same rows again, with settings that differ only
where the first fit does not read them (the model list, the predicted-error poses,
the guardrails, the printed size): the same first fit, twice, on the identify stage's
serial path (10 ms of 0.13 s on the 72-touch-up cell). :func:`first_fit` keeps the
last few first fits of this process by a digest of what decides them: the model,
the robot, the rows as the fit reads them and every setting but :data:`NOT_READ`.
A fit is deterministic in these, so a kept one is the fit that would be made.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from pipeline.measurement.data import FitData
from pipeline.stages.identify.types import IdentifyConfig, IdentifyResult, Robot

#: settings a prediction-only first fit does not read: the model (a key of its own), the
#: known distances (read as the rows' resolved ``FitData.dist``), what only the full fit's
#: uncertainty, the guardrails or the summary read, and the number of processes
NOT_READ = frozenset(
    {
        "model",
        "distances",
        "strict_distances",
        "n_workspace",
        "target_diameter_m",
        "implied_target_diameter_m",
        "pin_offset_cov_m2",
        "accept_implausible",
        "check_plausibility",
        "workers",
    }
)

#: first fits kept (the outliers stage's last search step's is the one identify meets)
KEEP = 4

_KEPT: OrderedDict[str, IdentifyResult] = OrderedDict()


def fit_key(name: str, robot: Robot, data: FitData, config: IdentifyConfig) -> str:
    """Digest of what decides a prediction-only fit of model ``name`` to ``data``."""
    h = hashlib.sha256()
    chain = robot.chain
    for text in (name, robot.urdf, chain.base_link, chain.tip_link, str(data.K)):
        h.update(text.encode() + b"\0")
    for arr in (data.q, data.d, data.sw, data.tk):
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype.str}{a.shape}".encode() + b"\0" + a.tobytes())
    h.update(repr([(int(a), int(b), float(m)) for a, b, m in data.dist]).encode() + b"\0")
    h.update(repr(list(data.target_ids)).encode() + b"\0")
    settings = {
        f.name: getattr(config, f.name)
        for f in dataclasses.fields(config)
        if f.name not in NOT_READ
    }
    h.update(repr(sorted(settings.items())).encode())
    return h.hexdigest()


def first_fit(
    fit: Callable[[str, IdentifyConfig], IdentifyResult],
    name: str,
    robot: Robot,
    data: FitData,
    config: IdentifyConfig,
) -> IdentifyResult:
    """``fit(name, config)`` (a fit of ``robot`` to ``data``), or the same first fit kept
    from earlier in this process.

    ``config`` is a first fit's (``prediction_only``, nominal correction frame, no print
    shape); the result is shared, not copied: its reader
    (:func:`pipeline.stages.identify.frame.correction_frame`) only reads it.
    """
    if not (config.prediction_only and config.correction_frame == "nominal"):
        return fit(name, config)
    key = fit_key(name, robot, data, config)
    kept = _KEPT.get(key)
    if kept is not None:
        _KEPT.move_to_end(key)
        return kept
    result = fit(name, config)
    _KEPT[key] = result
    while len(_KEPT) > KEEP:
        _KEPT.popitem(last=False)
    return result


def forget() -> None:
    """Drop every kept first fit (tests)."""
    _KEPT.clear()
