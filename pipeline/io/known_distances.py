"""Known distances between targets: the ``known_distances`` metadata and ``--distance``.

The form is ``A:B=METRES`` items joined by ``;`` (``spec/recording.md``);
labels are the targets' first-touch order 0, 1, 2, ..., or, when the metadata
has ``target_order`` (the cell's own names of the targets in first-touch order,
joined by ``,``), those names: a cell can name its bar before the plan that
fixes the visiting order exists. Names are translated to the first-touch
labels here (:func:`metadata_distances`), so the stages see one kind of label.
"""

from __future__ import annotations

import re
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


#: a target name of ``target_order``: letters, digits, ``_``, ``-``
NAME = re.compile(r"^[A-Za-z0-9_-]+$")


def target_order(text: str) -> list[str]:
    """The names of a ``target_order`` value (first-touch order); BadInput when malformed."""
    names = [n.strip() for n in text.split(",")]
    bad = [n for n in names if not NAME.match(n)]
    if bad or not names:
        raise BadInput(
            f"target_order {text!r}: names are letters, digits, '_' and '-', joined by ','"
        )
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise BadInput(f"target_order {text!r}: name(s) {dup} appear more than once")
    return names


def metadata_distances(metadata: Any) -> list[tuple[int | str, int | str, float]]:
    """The known distances of a recording's ``touchup`` metadata (``known_distances``,
    :func:`parse_distances`); [] without metadata or the key.

    With ``target_order`` the labels are its names, translated to first-touch
    labels (the name's position); a label that is not a name is refused, listing them.
    """
    meta = metadata or {}
    out = parse_distances(str(meta.get("known_distances", "") or ""))
    order = meta.get("target_order")
    if not order or not out:
        return out
    names = target_order(str(order))
    index = {n: k for k, n in enumerate(names)}

    def label(x: int | str, a: int | str, b: int | str, m: float) -> int:
        if str(x) not in index:
            raise BadInput(
                f"known distance {a}:{b}={m:g}: no target {str(x)!r} in target_order {names}"
            )
        return index[str(x)]

    return [(label(a, a, b, m), label(b, a, b, m), m) for a, b, m in out]
