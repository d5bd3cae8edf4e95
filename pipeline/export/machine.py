"""Every export in one JSON document (format ``json``), for programs.

Keys: ``format`` (``"vtcal-export"``), ``provenance`` (the URDF block's
``key: value`` pairs), ``model``, ``chain`` (``base_link``, ``flange_link``,
``joints``), ``p_flange_pin_m``, ``urdf`` (the text), ``ur_calibration``
(``entries``: segment -> ``{x, y, z, roll, pitch, yaw}``, ``end_frame``,
``hash``), ``offsets`` (:func:`pipeline.export.offsets.offsets_data`),
``calibration`` (the run's ``calibration.json``: the model predictions use, whole,
or null), ``urdf_holds`` (one sentence: whether the URDF is that model or its rigid
stand-in) and ``dh`` (``rows``: one ``{joint, alpha, beta, a, theta, d, hayati}`` per joint,
``base`` and ``tool`` as 4 x 4 row lists, ``convention``). A format the robot
does not allow is ``{"refused": "<the one-line reason>"}`` in place of its
value. Floats are written with full precision; SI units (m, rad).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from typing import Any

from pipeline.errors import ExportRefused
from pipeline.export.calibration import RunCalibration
from pipeline.export.dh import COLUMNS, mdh_table
from pipeline.export.offsets import offsets_data
from pipeline.export.ur import ur_entries, ur_hash

DH_CONVENTION = (
    "T_base_flange(q) = base * prod_i [Rx(alpha_i) Ry(beta_i) Tx(a_i) Rz(theta_i + q_i) Tz(d_i)]"
    " * tool (modified DH, Craig; Hayati's beta on nearly parallel axes)"
)


def _or_refused(fn: Callable[[], Any]) -> Any:
    try:
        return fn()
    except ExportRefused as exc:
        return {"refused": str(exc)}


def _ur(cal: RunCalibration) -> dict[str, Any]:
    entries, end = ur_entries(cal.chain)
    keys = ("x", "y", "z", "roll", "pitch", "yaw")
    return {
        "entries": {
            seg: dict(zip(keys, (float(v) for v in (*xyz, *rpy)), strict=True))
            for seg, (xyz, rpy) in entries.items()
        },
        "end_frame": end,
        "hash": ur_hash(entries),
    }


def _dh(cal: RunCalibration) -> dict[str, Any]:
    rows, T0, Tf, hayati = mdh_table(cal.chain)
    return {
        "convention": DH_CONVENTION,
        "rows": [
            {"joint": name, **dict(zip(COLUMNS, map(float, r), strict=True)), "hayati": bool(h)}
            for name, r, h in zip(cal.chain.joint_names, rows, hayati, strict=True)
        ],
        "base": T0.tolist(),
        "tool": Tf.tolist(),
    }


def _urdf_holds(cal: RunCalibration) -> str:
    """What ``urdf`` (and every other format here) carries, against the model predictions use."""
    rec = cal.record or {}
    used = rec.get("model")
    if not used or used == cal.model:
        return f"the model predictions use ({cal.model})"
    return (
        f"the rigid model {cal.model} only: predictions use {used}, whose configuration-"
        "dependent terms (joint compliance) no URDF, DH table or offset list can carry; "
        "'calibration' holds it (vtcal predict / vtcal compensate, pipeline.use.load)"
    )


def export_json(cal: RunCalibration, signs: Sequence[int] | None = None) -> str:
    """The JSON document (see module docstring)."""
    doc = {
        "format": "vtcal-export",
        "provenance": cal.provenance,
        "model": cal.model,
        "chain": {
            "base_link": cal.base_link,
            "flange_link": cal.flange_link,
            "joints": cal.chain.joint_names,
        },
        "p_flange_pin_m": [float(v) for v in cal.p_flange_pin],
        "urdf": cal.calibrated_urdf,
        "ur_calibration": _or_refused(lambda: _ur(cal)),
        "offsets": _or_refused(lambda: offsets_data(cal, signs)),
        "dh": _or_refused(lambda: _dh(cal)),
        "calibration": cal.record,
        "urdf_holds": _urdf_holds(cal),
    }
    return json.dumps(doc, indent=1, sort_keys=True, allow_nan=False) + "\n"
