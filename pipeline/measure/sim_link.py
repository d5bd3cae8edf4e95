"""``sim:SCENARIO.toml:SEED``: the simulated cell in process, as a :class:`CellLink`."""

from __future__ import annotations

from pipeline.errors import BadInput
from pipeline.measure.adapters import CellLink


def parse_sim(spec: str) -> tuple[str, int]:
    """``(scenario path, seed)`` of ``sim:SCENARIO.toml:SEED``."""
    body = spec.removeprefix("sim:")
    path, sep, seed = body.rpartition(":")
    if not sep or not path or not seed.lstrip("-").isdigit():
        raise BadInput(f"--robot {spec!r}: expected sim:SCENARIO.toml:SEED")
    return path, int(seed)


def connect_sim(spec: str) -> CellLink:
    raise BadInput(f"--robot {spec!r}: the simulated cell adapter is not available yet")
