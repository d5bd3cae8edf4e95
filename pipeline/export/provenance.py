"""Provenance of a calibration: the comment block at the top of ``calibrated.urdf``.

A calibrated URDF travels alone (to a MoveIt config, a robot driver, a colleague);
the block says where it came from and how good it is, in the file itself::

    <!-- vtcal provenance
      vtcal version: 0.1.0
      run id: 5c1f0e9a2b7d4e11
      source: recording sample.mcap, sha256 (first 16 hex) 9f1c...
      recorded: 2026-09-21 08:00 UTC
      shipped model: mdh
      validated accuracy: 0.1280 mm RMS held-out (k-fold, 18 touch-ups)
      predicted accuracy: 0.0993 mm RMS shape, 0.1116 mm RMS absolute
      ...
    -->

It is byte-deterministic: the same recording, options and code give the same
file wherever and whenever they run (``tests/test_determinism.py``). Hence the
*date* is the recording's (the earliest image stamp, UTC, the date the report
shows), never the wall clock of the calibration; the run id is a hash of the
run request (the run ledger's fingerprint: recording hash, options, vtcal
version and code), never a path or a time. The wall-clock time a file was
written is its modification time.

Pure functions on text; the choose stage (:mod:`pipeline.stages.choose.stage`)
stamps the shipped URDF and the runner writes it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from pipeline.accuracy.verdict import verdict

#: first line of the block; :func:`stamp_urdf` replaces a block that starts with it
MARKER = "vtcal provenance"
_BLOCK = re.compile(r"<!-- " + MARKER + r"\b.*?-->\n?", re.DOTALL)
_ROBOT = re.compile(r"<robot[\s>]")


@dataclass(frozen=True)
class Source:
    """What a calibration was computed from.

    Attributes
    ----------
    kind : ``"recording"`` or ``"touch-up table"``
    name : file name (no folder: the same bytes give the same block anywhere)
    sha256 : first 16 hex digits of the file's SHA-256, as the run ledger records it
    run_id : 16 hex digits identifying the run request (see module docstring)
    recorded_utc : ``YYYY-MM-DD HH:MM UTC`` of the earliest stamp, or None if unknown
    """

    kind: str
    name: str
    sha256: str
    run_id: str
    recorded_utc: str | None = None


def _mm(v: Any) -> str:
    return f"{float(v):.4f} mm" if isinstance(v, (int, float)) and v == v else "n/a"


def provenance_lines(summary: dict[str, Any], source: Source, version: str) -> list[str]:
    """The ``key: value`` lines of the block, from identify.json and the source.

    Parameters
    ----------
    summary : identify.json (top level = the shipped model's figures, ``crossval``
        once cross-validated)
    source : what the run read
    version : vtcal's version

    Returns
    -------
    list of str, one ``key: value`` line each (no comment delimiters).
    """
    v = verdict(summary) or {}
    model = str(summary.get("best_model") or summary.get("model") or "unknown")
    cv = ((summary.get("crossval") or {}).get("models") or {}).get(model) or {}
    validated = (
        f"{_mm(v['validated_mm'])} RMS {v.get('validated_how', 'held-out')}"
        if cv.get("kfold_rms_mm") is not None and v.get("validated_mm") is not None
        else "not cross-validated"
    )
    how = "chosen by held-out error" if summary.get("crossval") else "as asked"
    scale = (
        "held at the nominal robot's (no known distance): shape accuracy only"
        if summary.get("scale_held", True)
        else "identified from "
        + f"{len(summary.get('distances') or [])} known distance(s): absolute accuracy applies"
    )
    date = (
        f"{source.recorded_utc} (the {source.kind}'s own time stamps"
        if source.recorded_utc
        else f"unknown (no time stamps in the {source.kind}"
    )
    return [
        f"vtcal version: {version}",
        f"run id: {source.run_id} (hash of the run request: source, options, vtcal version, code)",
        f"source: {source.kind} {source.name}, sha256 (first 16 hex) {source.sha256}",
        f"shipped model: {model} ({how})",
        f"validated accuracy: {validated}",
        "predicted accuracy: "
        f"{_mm(summary.get('predicted_shape_rms_mm'))} RMS shape, "
        f"{_mm(summary.get('predicted_absolute_rms_mm'))} RMS absolute "
        "(from the parameter covariance)",
        f"fit residual: {_mm(summary.get('rms_mm'))} RMS (training, not an accuracy)",
        f"length scale: {scale}",
        "base frame: held at nominal (touch-ups never identify it)",
        f"date: {date}; the calibration's wall-clock time is not written, so identical runs "
        "give identical files)",
        *_predictions_line(summary, model),
    ]


def _predictions_line(summary: dict[str, Any], model: str) -> list[str]:
    """Where the run predicts with a model the URDF cannot carry: the URDF says it plainly."""
    used = (summary.get("crossval") or {}).get("predict_model")
    if not used or used == model:
        return []
    return [
        f"predictions: {used} (calibration.json), not this URDF: it holds the rigid model "
        f"{model} only, {used}'s joint compliance (a deflection with the gravity torque) no "
        "URDF can carry; vtcal predict / vtcal compensate / pipeline.use.load use it"
    ]


def _comment_safe(text: str) -> str:
    """XML comments may not hold ``--``."""
    while "--" in text:
        text = text.replace("--", "- -")
    return text


def stamp_urdf(urdf_xml: str, lines: list[str]) -> str:
    """The URDF with its provenance block replaced (or added) just before ``<robot``.

    Everything else is kept byte for byte; stamping twice with the same lines
    gives the same text.

    Raises
    ------
    ValueError
        If the text has no ``<robot`` element.
    """
    text = strip_provenance(urdf_xml)
    m = _ROBOT.search(text)
    if m is None:
        raise ValueError("not a URDF: no <robot> element")
    body = "\n".join(f"  {_comment_safe(line)}" for line in lines)
    block = f"<!-- {MARKER}\n{body}\n-->\n"
    return text[: m.start()] + block + text[m.start() :]


def strip_provenance(urdf_xml: str) -> str:
    """The URDF without its provenance block (what the identify stage wrote)."""
    return _BLOCK.sub("", urdf_xml)


def read_provenance(urdf_xml: str) -> dict[str, str]:
    """The ``key: value`` pairs of a URDF's provenance block (empty if it has none)."""
    m = _BLOCK.search(urdf_xml)
    if m is None:
        return {}
    out: dict[str, str] = {}
    for line in m.group(0).splitlines()[1:-1]:
        key, sep, value = line.strip().partition(": ")
        if sep:
            out[key] = value
    return out


def recorded_utc(stamps_ns: Any) -> str | None:
    """``YYYY-MM-DD HH:MM UTC`` of the earliest positive stamp (ns since the epoch), or None.

    The same rule as the report's date (:meth:`pipeline.report.data.RunData.date`):
    the recording's own time, never the wall clock.
    """
    import datetime as dt

    vals = [int(s) for s in stamps_ns if s is not None and s == s and int(s) > 0]
    if not vals:
        return None
    t = dt.datetime.fromtimestamp(min(vals) / 1e9, tz=dt.UTC)
    return t.strftime("%Y-%m-%d %H:%M UTC")
