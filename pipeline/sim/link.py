"""``sim:SCENARIO.toml:SEED``: the simulated cell as a :class:`CellLink`, in process or served.

The simulated robot runs on a simulated clock and emits its joint samples
(``joint_rate_hz`` of the scenario, encoder noise included) to a recorder;
:class:`JointTap` is that recorder here: it keeps the ``/joint_states``
samples, for :meth:`JointTap.drain` (in process) or :meth:`JointTap.since`
(the reference server's ``JOINTLOG?``), and drops everything else (the client
of the adapter writes the recording).
"""

from __future__ import annotations

import bisect
from typing import Any

import numpy as np

from pipeline.errors import BadInput
from pipeline.io.mcap_write import NullRecorder
from pipeline.live.cell_link import CellLink
from pipeline.live.protocols import JointReading

NS = 1_000_000_000


class JointTap(NullRecorder):
    """A recorder that keeps only the joint samples the simulated robot emits."""

    def __init__(self) -> None:
        super().__init__()
        self.samples: list[JointReading] = []
        self._stamps: list[int] = []
        self._drained = 0

    def push(
        self, log_time_ns: int, topic: str, datatype: str, msg: dict[str, Any], on_write: Any = None
    ) -> None:
        if topic != "/joint_states":
            return
        st = msg["header"]["stamp"]
        t = int(st["sec"]) * NS + int(st["nanosec"])
        if self._stamps and t <= self._stamps[-1]:
            return
        self.samples.append(JointReading(np.asarray(msg["position"], dtype=float), t))
        self._stamps.append(t)

    def drain(self) -> list[JointReading]:
        """Samples emitted since the last call."""
        out = self.samples[self._drained :]
        self._drained = len(self.samples)
        return out

    def since(self, since_ns: int) -> list[JointReading]:
        """Samples with a stamp after ``since_ns``."""
        return self.samples[bisect.bisect_right(self._stamps, since_ns) :]


def parse_sim(spec: str) -> tuple[str, int]:
    """``(scenario path, seed)`` of ``sim:SCENARIO.toml:SEED``."""
    body = spec.removeprefix("sim:")
    path, sep, seed = body.rpartition(":")
    if not sep or not path or not seed.lstrip("-").isdigit():
        raise BadInput(f"--robot {spec!r}: expected sim:SCENARIO.toml:SEED")
    return path, int(seed)


def sim_cell(spec: str) -> tuple[Any, JointTap]:
    """The :class:`~pipeline.sim.cell_adapter.SimCell` of ``spec`` and its joint tap."""
    from pipeline.sim.cell_adapter import SimCell
    from pipeline.sim.scenario import load_scenario

    path, seed = parse_sim(spec)
    tap = JointTap()
    return SimCell.from_scenario(load_scenario(path), seed, rec=tap), tap


def connect_sim(spec: str) -> CellLink:
    """The in-process link to the simulated cell of ``spec``."""
    cell, tap = sim_cell(spec)
    return CellLink(
        cell.robot,
        cell.camera,
        tap.drain,
        cell.nominal_urdf,
        cell.served_metadata,
        f"simulated cell {spec} in process (joint states: the robot's own, simulated clock)",
    )


def write_plan(cell: Any, path: str) -> None:
    """The simulated cell's scenario plan as a ``vtcal measure --plan`` Parquet."""
    import pandas as pd

    names = cell.robot.joint_names
    rows = [
        {"target_id": int(t), **dict(zip(names, map(float, q), strict=True))} for t, q in cell.plan
    ]
    pd.DataFrame(rows, columns=["target_id", *names]).to_parquet(path)
