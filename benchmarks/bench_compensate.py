"""vtcal compensate and vtcal predict: round trip, and against the truth on simulated cells.

Simulated cells (seeded; the seeds here are not the tests'): a robot with
random kinematic deviations (the simulator's magnitudes), touch-ups of 5
targets x 16 with 10 um / 1e-5 rad noise, ``vtcal identify`` with a known
distance (defaults, as a user calls it). Then 200 goal poses through the
touched volume (away from the wrist singularity, |q5| > 0.2 rad):

* **pin targets**: the positions the TRUE robot's pin takes at the goal joints;
  ``vtcal compensate`` from the goal joints plus 0.01 rad of error (a program
  that is a little off), then ``vtcal predict`` at the compensated joints:
  the round trip (predicted against target) and the true robot at the
  compensated joints against the targets, registered by one rigid motion
  (touch-ups never fix the base frame), next to the run's validated error and
  the program's own joints;
* **a nominal program**: the goal joints as a program on the nominal model;
  the calibrated flange at the compensated joints against the nominal flange
  poses (position and angle).

Real robot: each Panda dataset trained on its named placement, every other
placement's touch-ups compensated as a nominal program; the round trip and
the share of rows flagged outside the covered region.

    python benchmarks/bench_compensate.py
    python benchmarks/bench_compensate.py --seeds 201 202 --robots lrmate
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_positions,
    random_deviations,
    registered_errors,
    synthetic_touchups,
    workspace_poses,
)
from pipeline.cli import cli
from pipeline.kinematics import load_chain
from pipeline.kinematics.chain import fk
from pipeline.robots import builtin_urdf
from pipeline.use import load

REPO = Path(__file__).resolve().parent.parent
REAL = REPO / "datasets" / "real" / "mukca"
TRAIN = {"panda_2": "front_center", "panda_3": "frontcenter", "panda_4": "front"}
PIN = np.array([0.0167, -0.0101, 0.2524])
CENTRE = {
    "lrmate": np.array([-0.73, 0.18, -0.45, 0.34, -0.57, -0.32]),
    "ur5e": np.array([0.3, -1.2, 1.3, -1.6, -1.5, 0.3]),
}


def vtcal(*args: object) -> str:
    res = CliRunner().invoke(cli, [str(a) for a in args], prog_name="vtcal")
    if res.exit_code != 0:
        raise RuntimeError(f"vtcal {args[0]} failed ({res.exit_code}): {res.output}")
    return res.output


def rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(v) ** 2)))


def simulated(robot: str, seed: int, work: Path) -> dict[str, float]:
    """The figures of one simulated cell (see the module docstring), mm and s."""
    urdf = builtin_urdf(robot)
    nominal = load_chain(urdf, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(nominal, random_deviations(nominal, rng))
    table, targets = synthetic_touchups(
        true, PIN, 5, 16, rng, noise_q_rad=1e-5, noise_pin_m=1e-5, q_centre=CENTRE[robot]
    )
    cell = work / f"{robot}_{seed}"
    cell.mkdir()
    (cell / "robot.urdf").write_text(urdf)
    table.to_csv(cell / "touchups.csv", index=False)
    d02 = float(np.linalg.norm(targets[0] - targets[2]))
    out = cell / "run"
    vtcal("identify", cell / "touchups.csv", "--urdf", cell / "robot.urdf", "--out", out,
          "--no-report", "--distance", f"0:2={d02!r}")  # fmt: skip
    names = nominal.joint_names
    q_goal = workspace_poses(table[names].to_numpy(float), 400, rng)
    q_goal = q_goal[np.abs(q_goal[:, 4]) > 0.2][:200]
    p_goal = pin_positions(true, PIN, q_goal)
    q_start = q_goal + rng.normal(0, 0.01, q_goal.shape)
    tab = pd.DataFrame(p_goal, columns=["x", "y", "z"])
    tab[names] = q_start
    tab.to_csv(cell / "targets.csv", index=False)
    t0 = time.perf_counter()
    vtcal("compensate", out, "--targets", cell / "targets.csv", "--out", cell / "comp.csv")
    seconds = time.perf_counter() - t0
    comp = pd.read_csv(cell / "comp.csv")
    comp[names].to_csv(cell / "joints.csv", index=False)
    vtcal("predict", out, "--joints", cell / "joints.csv", "--out", cell / "pred.csv")
    pred = pd.read_csv(cell / "pred.csv")[["pin_x_m", "pin_y_m", "pin_z_m"]].to_numpy(float)
    q_comp = comp[names].to_numpy(float)
    true_err = registered_errors(pin_positions(true, PIN, q_comp), p_goal, scale=False)
    own_err = registered_errors(pin_positions(true, PIN, q_start), p_goal, scale=False)
    # the goal joints as a nominal program: flange poses
    pd.DataFrame(q_goal, columns=names).to_csv(cell / "program.csv", index=False)
    vtcal("compensate", out, "--targets", cell / "program.csv", "--out", cell / "prog.csv")
    prog = pd.read_csv(cell / "prog.csv")
    back = load(out).forward(prog[names].to_numpy(float)).T_base_flange
    T_nom = fk(nominal, q_goal)
    dR = np.einsum("nji,njk->nik", back[:, :3, :3], T_nom[:, :3, :3])
    angle = np.linalg.norm(Rotation.from_matrix(dR).as_rotvec(), axis=1)
    return {
        "model": str(load(out).model),
        "n": float(len(q_goal)),
        "converged": float(comp["converged"].mean()),
        "round_trip_mm": float(np.abs(pred - p_goal).max() * 1e3),
        "true_rms_mm": rms(true_err) * 1e3,
        "true_max_mm": float(true_err.max() * 1e3),
        "validated_mm": float(load(out).record["validated"]["validated_mm"]),
        "program_rms_mm": rms(own_err) * 1e3,
        "flange_mm": float(np.abs(back[:, :3, 3] - T_nom[:, :3, 3]).max() * 1e3),
        "flange_rad": float(angle.max()),
        "seconds_per_100": seconds / len(q_goal) * 100,
    }


def real(dataset: str, work: Path) -> dict[str, float]:
    """One Panda dataset: trained on its named placement, the others compensated."""
    df = pd.read_csv(REAL / f"{dataset}.csv")
    place = df["target_id"].str.split("/").str[0]
    train = TRAIN[dataset]
    d = work / dataset
    d.mkdir()
    df[place == train].to_csv(d / "train.csv", index=False)
    df[place != train].to_csv(d / "held.csv", index=False)
    out = d / "run"
    vtcal("identify", d / "train.csv", "--urdf", REAL / "nominal_panda.urdf", "--out", out,
          "--flange-link", "panda_hand_tcp", "--no-report",
          "--distance", f"{train}/hole_0:{train}/hole_1=0.05")  # fmt: skip
    vtcal("compensate", out, "--targets", d / "held.csv", "--out", d / "comp.csv")
    comp = pd.read_csv(d / "comp.csv")
    cal = load(out)
    held = df[place != train]
    back = cal.forward(comp[cal.joint_names].to_numpy(float)).T_base_flange
    T_nom = fk(cal.chain, held[cal.joint_names].to_numpy(float))
    return {
        "model": str(cal.model),
        "n": float(len(comp)),
        "converged": float(comp["converged"].mean()),
        "round_trip_mm": float(np.abs(back[:, :3, 3] - T_nom[:, :3, 3]).max() * 1e3),
        "outside": float((~comp["inside_region"]).mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", nargs="+", default=["lrmate", "ur5e"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[201, 202, 203])
    ap.add_argument("--no-real", action="store_true", help="skip the Panda datasets")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_compensate_") as tmp:
        work = Path(tmp)
        print("simulated cells: pin targets compensated, then predicted (mm)")
        print(
            f"{'robot':<8}{'seed':>5}{'model':>13}{'reached':>9}{'round trip':>12}"
            f"{'true rms':>10}{'true max':>10}{'validated':>11}{'program':>9}"
            f"{'nominal flange':>16}{'s/100':>7}"
        )
        ratios = []
        for robot in args.robots:
            for seed in args.seeds:
                f = simulated(robot, seed, work)
                ratios.append(f["true_rms_mm"] / f["validated_mm"])
                print(
                    f"{robot:<8}{seed:>5}{f['model']:>13}{f['converged']:>9.0%}"
                    f"{f['round_trip_mm']:>12.1e}{f['true_rms_mm']:>10.4f}{f['true_max_mm']:>10.4f}"
                    f"{f['validated_mm']:>11.4f}{f['program_rms_mm']:>9.3f}"
                    f"{f['flange_mm']:>8.0e}/{f['flange_rad']:.0e}{f['seconds_per_100']:>7.2f}"
                )
        print(
            f"true error / validated error: {min(ratios):.2f}-{max(ratios):.2f} "
            f"({sum(r <= 1 for r in ratios)} of {len(ratios)} within)"
        )
        if not args.no_real:
            print("\nreal Panda: held-out placements' touch-ups as a nominal program (mm)")
            for ds in TRAIN:
                f = real(ds, work)
                print(
                    f"{ds:<8} model {f['model']:<12} {int(f['n'])} rows, reached "
                    f"{f['converged']:.0%}, round trip {f['round_trip_mm']:.1e} mm, "
                    f"outside the covered region {f['outside']:.0%}"
                )
    print(f"total {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
