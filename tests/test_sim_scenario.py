"""Scenario files, plan-file poses, robots and bad input of the simulator."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.errors import BadInput
from pipeline.kinematics import fk, load_chain
from pipeline.robots import BUILTIN, builtin_urdf
from pipeline.sim.robot import deviated_origins, draw_deviations, solve_ik
from pipeline.sim.scenario import load_scenario
from pipeline.sim.simulator import write_recording

SCEN = Path(__file__).resolve().parents[1] / "datasets" / "scenarios"


@pytest.mark.parametrize("path", sorted(SCEN.glob("*.toml")), ids=lambda p: p.stem)
def test_scenarios_load(path: Path) -> None:
    sc = load_scenario(path)
    assert sc.name == path.stem
    assert sc.poses.per_target >= 1


def test_bad_scenarios_are_one_line_bad_input(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nwidht = 3\n")
    with pytest.raises(BadInput, match="unknown key 'widht'"):
        load_scenario(bad)
    bad.write_text("[targets]\npolarity = 'purple'\n")
    with pytest.raises(BadInput, match="polarity"):
        load_scenario(bad)
    bad.write_text("[camera\n")
    with pytest.raises(BadInput, match="not valid TOML"):
        load_scenario(bad)
    r = subprocess.run(
        [sys.executable, "-m", "pipeline", "simulate", "--scenario", str(bad), "--out",
         str(tmp_path / "x.mcap")],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "bad.toml" in r.stderr


@pytest.mark.parametrize("name", BUILTIN)
def test_builtin_robots_and_true_deviations(name: str) -> None:
    chain = load_chain(builtin_urdf(name), "base_link", "flange")
    assert chain.n_dof == (7 if name == "iiwa7" else 6)
    rng = np.random.default_rng(0)
    dev = draw_deviations(chain, rng)
    true = chain.with_origins(deviated_origins(chain, dev))
    q = rng.uniform(-1, 1, (20, chain.n_dof))
    d = np.linalg.norm(fk(true, q)[:, :3, 3] - fk(chain, q)[:, :3, 3], axis=1)
    assert 1e-4 < np.median(d) < 1e-2  # tenths of a mm to mm
    # nominal IK recovers a reachable pose
    q0 = np.clip(q[0] * 0.5, chain.lower, chain.upper)
    qs, ok = solve_ik(chain, fk(chain, q0), q0 + 0.05)
    assert ok and np.allclose(fk(chain, qs), fk(chain, q0), atol=1e-9)


def test_plan_file_poses(tmp_path: Path) -> None:
    sc = load_scenario(SCEN / "small.toml")
    sc = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, per_target=1))
    t1 = write_recording(sc, 3, tmp_path / "a.mcap")
    names = t1["joint_names"]
    rows = [
        dict(target_id=tu["target"], **dict(zip(names, tu["q"], strict=True)))
        for tu in t1["touchups"]
    ]
    rows = rows[::-1]  # touch the targets in the opposite order
    plan = tmp_path / "plan.parquet"
    pd.DataFrame(rows).to_parquet(plan)
    sc2 = dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, plan=str(plan)))
    t2 = write_recording(sc2, 3, tmp_path / "b.mcap")
    assert [tu["target"] for tu in t2["touchups"]] == [r["target_id"] for r in rows]
    # labels follow the first-touch order
    assert [tu["label"] for tu in t2["touchups"]] == list(range(len(rows)))
    assert all(tu["converged"] for tu in t2["touchups"])
    assert t2["metadata"]["known_distances"].startswith("0:2=")
    bad = tmp_path / "bad.parquet"
    pd.DataFrame({"target_id": [0]}).to_parquet(bad)
    with pytest.raises(BadInput, match="plan lacks columns"):
        write_recording(
            dataclasses.replace(sc, poses=dataclasses.replace(sc.poses, plan=str(bad))),
            3,
            tmp_path / "c.mcap",
        )
