"""Joint zero offsets (mastering corrections) and the TCP, for controllers with their own kinematics.

A FANUC, ABB, KUKA, ... controller computes its kinematics from the maker's
nominal model; only the joint zeros (mastering / calibration offsets) and the
tool centre point are the user's to set. What fits that is not the shipped
model cut down (dropping its link-geometry corrections leaves its zero offsets
compensating for geometry that is no longer there) but the ``offsets`` error
model vtcal identifies beside the others: the zero offsets and the virtual
pin that best explain the touch-ups WITH the nominal link geometry
(``parameters.parquet``, ``model == "offsets"``). What dropping the geometry
costs is the difference between its figures and the shipped model's
(training residual and held-out error, from identify.json).

Sign convention: vtcal's joint value is the joint_states value, positive about
the URDF axis, and the identified true angle is

    q_true = q_reported + dq0                                              (1)

(:mod:`pipeline.models.offsets`). A controller whose joint ``k`` counts the
other way (``s_k = -1``) reports ``q_c = s_k q`` and needs
``dq0_c = s_k dq0``: ``--joint-signs`` gives the ``s_k``. The TCP is in the
NOMINAL flange frame (the controller's flange at the mastered zero), metres
and millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from pipeline.errors import BadInput, ExportRefused
from pipeline.export.calibration import RunCalibration, header_lines
from pipeline.io.run_folder import RUN_FILES


def parse_signs(text: str | None, n: int) -> list[int]:
    """``"+1,-1,..."`` (one per joint) -> list of +-1; None or empty -> all +1.

    Raises
    ------
    BadInput
        Not ``n`` comma-separated values, or a value other than +1 / -1.
    """
    if not text:
        return [1] * n
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != n:
        raise BadInput(f"--joint-signs {text!r}: {len(parts)} value(s) for {n} joints")
    out = []
    for p in parts:
        if p not in ("1", "+1", "-1"):
            raise BadInput(f"--joint-signs {text!r}: {p!r} is not +1 or -1")
        out.append(-1 if p == "-1" else 1)
    return out


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else None


def offsets_data(cal: RunCalibration, signs: Sequence[int] | None = None) -> dict[str, Any]:
    """Zero offsets, TCP and the cost of dropping the geometry, as plain values.

    Returns
    -------
    dict with ``joints`` (list of ``{name, sign, offset_rad|offset_m, offset_deg,
    std_rad, identifiable}``), ``tcp_flange_m`` (3,), ``tcp_flange_mm`` (3,),
    ``flange_link``, ``cost`` (offsets model vs shipped model: training RMS and
    held-out RMS, mm) and ``note``.

    Raises
    ------
    ExportRefused
        The run has no ``offsets`` model (identified with ``--model`` other than
        ``all`` or ``offsets``).
    """
    fit = cal.offsets
    if fit is None:
        raise ExportRefused(
            f"offsets: {cal.run_dir / RUN_FILES['parameters']} has no 'offsets' model "
            "(identify with --model all, the default, or --model offsets)"
        )
    s = list(signs) if signs is not None else [1] * len(fit.joints)
    joints = []
    for k, name in enumerate(fit.joints):
        v = s[k] * float(fit.dq0[k])
        row: dict[str, Any] = {
            "name": name,
            "sign": s[k],
            "identifiable": bool(fit.identifiable[k]),
        }
        if fit.units[k] == "m":
            row["offset_m"] = v
        else:
            row["offset_rad"] = v
            row["offset_deg"] = math.degrees(v)
        row["std"] = _num(fit.std[k])
        joints.append(row)
    models = cal.summary.get("models") or {}
    cv = (cal.summary.get("crossval") or {}).get("models") or {}
    shipped = cal.model

    def fig(model: str, src: dict[str, Any], key: str) -> float | None:
        return _num((src.get(model) or {}).get(key))

    cost = {
        "shipped_model": shipped,
        "offsets_fit_rms_mm": fig("offsets", models, "rms_mm"),
        "shipped_fit_rms_mm": fig(shipped, models, "rms_mm") or _num(cal.summary.get("rms_mm")),
        "offsets_heldout_rms_mm": fig("offsets", cv, "kfold_rms_mm"),
        "shipped_heldout_rms_mm": fig(shipped, cv, "kfold_rms_mm"),
    }
    return {
        "flange_link": cal.flange_link,
        "joints": joints,
        "tcp_flange_m": [float(v) for v in fit.p_flange_pin],
        "tcp_flange_mm": [float(v) * 1e3 for v in fit.p_flange_pin],
        "cost": cost,
        "note": (
            "zero offsets and TCP identified with the NOMINAL link geometry (vtcal's offsets "
            "model); the shipped model's link-geometry corrections are dropped; "
            "q_true = q_reported + offset in each joint's sign convention; joints not "
            "identifiable from these touch-ups are 0 (absorbed by the base frame or the TCP)"
        ),
    }


def _f(v: float | None, unit: str = "mm") -> str:
    return f"{v:.4f} {unit}" if v is not None else "n/a"


def offsets_text(cal: RunCalibration, signs: Sequence[int] | None = None) -> str:
    """The offsets as a commented YAML document (see :func:`offsets_data`)."""
    d = offsets_data(cal, signs)
    c = d["cost"]
    lines = ["# joint zero offsets (mastering) and TCP, written by vtcal export (format: offsets)"]
    lines += [f"# {line}" for line in header_lines(cal)]
    lines += [
        "# For a controller that keeps its OWN (nominal) kinematics: these offsets and this TCP",
        "# were identified with the nominal link geometry. The link-geometry corrections of the",
        f"# shipped model ({c['shipped_model']}) are DROPPED; on this run's touch-ups that costs:",
        f"#   fit RMS {_f(c['offsets_fit_rms_mm'])} (offsets only) vs "
        f"{_f(c['shipped_fit_rms_mm'])} (shipped)",
        f"#   held-out RMS {_f(c['offsets_heldout_rms_mm'])} (offsets only) vs "
        f"{_f(c['shipped_heldout_rms_mm'])} (shipped)",
        "# Convention: q_true = q_reported + offset, per joint in the sign given (sign -1: the",
        "# controller counts that joint opposite to the URDF axis). Check on the robot with a",
        "# small move before use. Not identifiable joints are 0 and must stay as mastered.",
        f"flange_link: {d['flange_link']}",
        "joints:",
    ]
    for j in d["joints"]:
        lines.append(f"  - name: {j['name']}")
        lines.append(f"    sign: {j['sign']}")
        if "offset_m" in j:
            lines.append(f"    offset_m: {j['offset_m']!r}")
        else:
            lines.append(f"    offset_rad: {j['offset_rad']!r}")
            lines.append(f"    offset_deg: {j['offset_deg']!r}")
        lines.append(f"    identifiable: {str(j['identifiable']).lower()}")
    lines.append("# TCP (virtual pin) in the NOMINAL flange frame")
    lines.append("tcp_flange_m: [" + ", ".join(repr(v) for v in d["tcp_flange_m"]) + "]")
    lines.append("tcp_flange_mm: [" + ", ".join(repr(v) for v in d["tcp_flange_mm"]) + "]")
    return "\n".join(lines) + "\n"
