"""What a measurement did, in figures: counts, captures and times of its touch-ups.

``vtcal measure`` prints it as one line, ``vtcal calibrate`` keeps it in
``measure.json``, and the recording carries it as its MCAP metadata record
``measurement`` (:func:`as_metadata`), so that ``vtcal run`` on the recording
(``recording.json``, the report) says how it was measured, whoever runs it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.live.timing import PHASES

#: name of the recording's metadata record that holds :func:`as_metadata`
METADATA_NAME = "measurement"


def summarize(
    touchups: list[dict[str, Any]], n_plan: int, sessions: int, out: Path
) -> dict[str, Any]:
    """Counts and times of a measurement from its touch-up summaries (all sessions).

    ``cell_s`` is split into ``travel_s``, ``settle_s``, ``servo_s`` and ``capture_s``
    (:mod:`pipeline.live.timing`) when every touch-up carries its split (a
    recording resumed from an older version's does not).
    """
    conv = [t for t in touchups if t["converged"]]
    reasons: dict[str, int] = {}
    for t in touchups:
        if not t["converged"]:
            reasons[t["reason"]] = reasons.get(t["reason"], 0) + 1
    keys = [f"{p}_s" for p in PHASES]
    split = (
        {k: sum(t[k] for t in touchups) for k in keys}
        if touchups and all(k in t for t in touchups for k in keys)
        else {}
    )
    return {
        "recording": str(out),
        "n_plan": n_plan,
        "touchups": len(touchups),
        "converged": len(conv),
        "gave_up": reasons,
        "cell_s": sum(t["cell_s"] for t in touchups),
        **split,
        "wall_s": sum(t["wall_s"] for t in touchups),
        "captures": sum(t["captures"] for t in touchups),
        "captures_per_converged": (
            sum(t["captures"] for t in touchups) / len(conv) if conv else None
        ),
        "sessions": sessions,
    }


def summary_line(s: dict[str, Any]) -> str:
    """One line: how many touch-ups converged and how long measuring took."""
    gave = ", ".join(f"{k} {v}" for k, v in s["gave_up"].items()) or "none"
    split = ", ".join(f"{p} {s[p + '_s']:.1f}" for p in PHASES if p + "_s" in s)
    return (
        f"measured {s['touchups']}/{s['n_plan']} touch-ups: {s['converged']} converged "
        f"(gave up: {gave}); {s['captures']} captures; measuring took {s['cell_s']:.1f} s "
        f"cell time"
        + (f" ({split} s)" if split else "")
        + f", {s['wall_s']:.1f} s wall time"
        + (f" over {s['sessions']} sessions" if s["sessions"] > 1 else "")
    )


def as_metadata(s: dict[str, Any]) -> dict[str, str]:
    """The summary as an MCAP metadata record (a string map: numbers as text, the
    give-up reasons as a JSON object).

    Left out: the recording's own path, and the wall time (how fast the measuring
    computer ran, not what the cell did: a recording holds the cell clock only, so
    the same cell measured twice gives the same bytes).
    """
    return {
        k: (json.dumps(v) if isinstance(v, dict) else f"{v}")
        for k, v in s.items()
        if k not in ("recording", "wall_s")
    }


def from_metadata(kv: dict[str, str]) -> dict[str, Any]:
    """Inverse of :func:`as_metadata` (unknown keys kept as text)."""
    out: dict[str, Any] = {}
    for k, v in kv.items():
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out
