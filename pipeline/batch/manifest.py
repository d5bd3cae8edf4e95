"""What a batch runs: items from paths or a dataset manifest (``vtcal batch --manifest``)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import BadInput

if TYPE_CHECKING:
    pass


NAME_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class BatchItem:
    """One recording of a batch.

    Attributes
    ----------
    name : run folder name under the batch output folder (unique within the batch)
    recording : path of the MCAP recording (absolute once resolved)
    robot : robot the manifest says recorded it ('' when not given)
    notes : free text from the manifest
    simulate : ``(scenario TOML, seed)`` when the manifest says how to make the recording
        with ``vtcal simulate``: the batch's worker writes it first if it is missing
    robot_id : the physical robot (cell) that recorded it, for ``vtcal audit`` ('' when not
        given; the recording's own ``robot_id`` metadata key wins)
    """

    name: str
    recording: Path
    robot: str = ""
    notes: str = ""
    simulate: tuple[str, int] | None = None
    robot_id: str = ""


@dataclass(frozen=True)
class Manifest:
    """A dataset manifest: ``datasets/NAME.toml``."""

    path: Path
    name: str
    description: str
    items: tuple[BatchItem, ...]


def _unique_names(stems: Sequence[str]) -> list[str]:
    """Make run folder names unique in order: ``a, a, b -> a, a-2, b``.

    The first occurrence keeps its stem; a repeat gets the smallest ``-k`` suffix
    that is neither another stem nor already used.
    """
    taken = set(stems)
    used: set[str] = set()
    out = []
    for s in stems:
        name, k = s, 1
        while name in used or (k > 1 and name in taken):
            k += 1
            name = f"{s}-{k}"
        used.add(name)
        out.append(name)
    return out


def items_from_paths(paths: Sequence[str | os.PathLike[str]]) -> list[BatchItem]:
    """Batch items for recordings given on the command line.

    Each is named after the file stem (``cell3.mcap -> cell3``); repeated stems get
    ``-2``, ``-3``... in the order given. Missing files are not an error here:
    they fail in their own task and show in the summary.
    """
    ps = [Path(p).expanduser().absolute() for p in paths]
    names = _unique_names([p.stem or "recording" for p in ps])
    return [BatchItem(n, p) for n, p in zip(names, ps, strict=True)]


def load_manifest(path: str | os.PathLike[str]) -> Manifest:
    """Read a dataset manifest (TOML).

    Format (paths relative to the manifest's folder)::

        name = "fleet_demo"
        description = "..."

        [[recordings]]
        path = "fleet_demo/cell1.mcap"   # required
        name = "cell1"                   # optional run folder name (default: file stem)
        robot = "lrmate"                 # optional
        robot_id = "cell1-SN123"         # optional: the physical robot (vtcal audit)
        notes = "after the J2 gearbox swap"   # optional
        simulate = { scenario = "scenarios/standard.toml", seed = 11 }   # optional: see below

    ``simulate``: a recording that is missing is first simulated (``vtcal simulate
    --scenario SCENARIO --seed SEED --out PATH``, the scenario's path relative to the
    manifest), so a demo manifest runs as written on a fresh clone.

    Raises
    ------
    BadInput
        One line naming the manifest and what is wrong (unreadable TOML, no
        ``[[recordings]]``, an entry without ``path``, a bad or repeated ``name``).
    """
    import tomllib

    p = Path(path)
    if not p.is_file():
        raise BadInput(f"{p}: no such manifest file")
    try:
        raw = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BadInput(f"{p}: not a readable TOML manifest: {exc}") from exc
    recs = raw.get("recordings")
    if not isinstance(recs, list) or not recs:
        raise BadInput(f"{p}: no [[recordings]] entries")
    base = p.parent.absolute()
    paths: list[Path] = []
    given: list[str | None] = []
    extra: list[tuple[str, str, tuple[str, int] | None, str]] = []
    for i, r in enumerate(recs):
        where = f"{p}: recordings[{i}]"
        if not isinstance(r, dict) or not isinstance(r.get("path"), str) or not r["path"]:
            raise BadInput(f"{where}: needs a 'path' string")
        unknown = set(r) - {"path", "name", "robot", "robot_id", "notes", "simulate"}
        if unknown:
            raise BadInput(f"{where}: unknown key(s) {', '.join(sorted(unknown))}")
        for key in ("name", "robot", "robot_id", "notes"):
            if key in r and not isinstance(r[key], str):
                raise BadInput(f"{where}: '{key}' must be a string, got {r[key]!r}")
        if "name" in r and not NAME_OK.match(r["name"]):
            raise BadInput(f"{where}: name {r['name']!r} is not a plain folder name")
        rp = Path(r["path"]).expanduser()
        paths.append(rp if rp.is_absolute() else base / rp)
        given.append(r.get("name"))
        extra.append(
            (
                r.get("robot", ""),
                r.get("notes", ""),
                _simulate(r, base, where),
                r.get("robot_id", ""),
            )
        )
    explicit = [g for g in given if g]
    dup = sorted({g for g in explicit if explicit.count(g) > 1})
    if dup:
        raise BadInput(f"{p}: repeated recording name(s) {', '.join(dup)}")
    names = _unique_names([g or q.stem for g, q in zip(given, paths, strict=True)])
    items = tuple(
        BatchItem(n, q, robot, notes, sim, rid)
        for n, q, (robot, notes, sim, rid) in zip(names, paths, extra, strict=True)
    )
    return Manifest(
        path=p,
        name=str(raw.get("name", p.stem)),
        description=str(raw.get("description", "")),
        items=items,
    )


def _simulate(entry: dict[str, object], base: Path, where: str) -> tuple[str, int] | None:
    """An entry's ``simulate = { scenario = "...", seed = N }``: (absolute scenario, seed)."""
    sim = entry.get("simulate")
    if sim is None:
        return None
    if (
        not isinstance(sim, dict)
        or set(sim) != {"scenario", "seed"}
        or not isinstance(sim["scenario"], str)
        or not isinstance(sim["seed"], int)
        or isinstance(sim["seed"], bool)
    ):
        raise BadInput(
            f"{where}: 'simulate' must be {{ scenario = \"FILE.toml\", seed = N }}, got {sim!r}"
        )
    sp = Path(sim["scenario"]).expanduser()
    sp = sp if sp.is_absolute() else base / sp
    if not sp.is_file():
        raise BadInput(f"{where}: simulate: no such scenario file {sp}")
    return str(sp), int(sim["seed"])


def ensure_recording(item: BatchItem) -> bool:
    """Simulate ``item``'s recording when it is missing and the manifest says how.

    Returns True when it simulated. The file and its ``.truth.json`` are written as
    ``vtcal simulate`` writes them (atomically: a killed batch leaves no partial file).
    """
    if item.simulate is None or item.recording.exists():
        return False
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import write_recording

    scenario, seed = item.simulate
    write_recording(load_scenario(Path(scenario)), seed, item.recording)
    return True
