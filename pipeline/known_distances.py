"""Known distances between targets: the ``known_distances`` metadata and ``--distance``.

The form is ``A:B=METRES`` items joined by ``;`` (``../shared/spec/recording.md``);
labels are the targets' first-touch order 0, 1, 2, ...
"""

from __future__ import annotations

from typing import Any

from pipeline.errors import BadInput


def _label(text: str) -> int | str:
    return int(text) if text.lstrip("-").isdigit() else text


def parse_distances(text: str) -> list[tuple[int | str, int | str, float]]:
    """Parse ``"A:B=METRES;C:D=METRES"`` (the ``known_distances`` metadata form).

    Returns
    -------
    list of ``(A, B, metres)`` labels as int where numeric.

    Raises
    ------
    BadInput
        On a malformed item or a non-positive distance.
    """
    out: list[tuple[int | str, int | str, float]] = []
    for item in filter(None, (s.strip() for s in text.replace(",", ";").split(";"))):
        pair, sep, metres = item.partition("=")
        a, sep2, b = pair.partition(":")
        try:
            d = float(metres)
        except ValueError:
            d = float("nan")
        if not sep or not sep2 or not a.strip() or not b.strip() or not d > 0:
            raise BadInput(f"known distance {item!r}: expected A:B=METRES with METRES > 0")
        out.append((_label(a.strip()), _label(b.strip()), d))
    return out


def metadata_distances(metadata: Any) -> list[tuple[int | str, int | str, float]]:
    """The known distances of a recording's ``touchup`` metadata (``known_distances``,
    :func:`parse_distances`); [] without metadata or the key."""
    return parse_distances(str((metadata or {}).get("known_distances", "") or ""))
