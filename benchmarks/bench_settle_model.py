"""Can a touch-up's three final captures tell the camera's swing after a move?

A flange camera still swinging after the last move of a touch-up puts an offset
into its final captures that the encoders do not see. ``touchup_settle`` weighs
the captures by their scatter; what is left is the swing still in the last one.
This benchmark asks whether a model of the swing could take that out too, and
shows why :mod:`pipeline.stages.touchups.swing` (which does, when the settle test
finds the camera swinging) takes the arm's decay and phase step from the pooled
second moments of the captures rather than from the least-squares cost.

Model (one mode, the usual picture of an arm ringing after a stop): the centre's
offset at the ``k``-th final capture (``k = 0, 1, 2``, equally spaced) is

    x_k = c + a r^k sin(phi + k Delta),     x, c, a in R^2 (u, v)

with one phase ``phi`` per touch-up shared by ``u`` and ``v`` (five unknowns
``c, a, phi`` for six numbers), and the decay per capture ``r`` and the phase
step ``Delta`` shared by every touch-up (the captures are equally spaced, so only
the step aliased into ``[0, pi]`` can be told). For each ``(r, Delta)`` on a grid
every touch-up's ``phi`` is searched on a grid and ``c, a`` solved by linear
least squares (:func:`pipeline.stages.touchups.swing.fit_one_mode`); the summed
squared residual is the fit's cost.

Run on the standard LR Mate-like cell (36 touch-ups) with the vibration of
``bench_optics.py`` and on its still twin (same seed), through ingest and the
touch-up stage. Printed: the cost over the grid (is ``(r, Delta)`` told by the
data?), the truth's ``(r, Delta)`` (15 Hz, 0.3 s decay, captures 0.21 s apart),
and the swing the best fit puts into the last capture on each cell: on the still
twin there is none to find, so what it finds there is noise the correction
would add.

    python benchmarks/bench_settle_model.py            # seed 7 (~1 min)
    python benchmarks/bench_settle_model.py --seed 8
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "benchmarks"))


def final_centres(rec: Path, out: Path) -> tuple[np.ndarray, float]:
    """``(n, 3, 2)`` centres of each touch-up's three final captures (time order) and
    their spacing (s), from the touch-up stage's ``converged_frame_indices``."""
    import pandas as pd

    from pipeline.run.orchestrator import RunConfig, run_pipeline

    run_pipeline(rec, out, RunConfig(report=False), until="touchups")
    tu = pd.read_parquet(out / "touchups.parquet")
    det = pd.read_parquet(out / "detections.parquet").set_index("frame_index")
    frames = pd.read_parquet(out / "frames.parquet").set_index("frame_index")
    blocks, dts = [], []
    for idx in tu["converged_frame_indices"]:
        idx = [int(i) for i in idx][-3:]
        if len(idx) == 3 and bool(det.loc[idx, "found"].all()):
            blocks.append(det.loc[idx, ["u", "v"]].to_numpy(float))
            dts += list(np.diff(frames.loc[idx, "stamp_ns"].to_numpy(np.int64)) / 1e9)
    return np.array(blocks), float(np.median(dts))


def fit(X: np.ndarray, r: float, delta: float) -> tuple[float, np.ndarray]:
    """Summed cost of the one-mode model at ``(r, delta)`` and the swing it puts into the
    last capture, ``(n, 2)`` px (:func:`pipeline.stages.touchups.swing.fit_one_mode`)."""
    from pipeline.stages.touchups.swing import fit_one_mode

    cost, _, swing = fit_one_mode(X, r, delta)
    return float(cost.sum()), swing


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    from bench_optics import CELLS, EFFECTS

    from pipeline.sim.scenario import scenario_from_dict
    from pipeline.sim.simulator import write_recording

    t_all = time.perf_counter()
    cells = {}
    with tempfile.TemporaryDirectory(prefix="bench_settle_") as tmp:
        for effect in ("vibration", "linear"):
            raw = tomllib.loads((REPO / "datasets" / "scenarios" / CELLS["lrmate"]).read_text())
            raw.setdefault("poses", {})["per_target"] = 12
            raw["optics"] = dict(EFFECTS[effect])
            sc = scenario_from_dict(raw, where=f"lrmate-{effect}", base_dir=str(REPO))
            rec = Path(tmp) / f"{effect}.mcap"
            write_recording(sc, args.seed, rec)
            cells[effect] = final_centres(rec, Path(tmp) / effect)
            optics = sc.optics
    X, dt = cells["vibration"]
    r_true = float(np.exp(-dt / optics.vibration_damping_s))
    d_true = float(np.angle(np.exp(2j * np.pi * optics.vibration_hz * dt)))
    d_true = abs(d_true)
    print(
        f"LR Mate-like cell, seed {args.seed}: {len(X)} touch-ups with three final captures "
        f"{dt:.3f} s apart; truth r = {r_true:.3f}, Delta = {np.degrees(d_true):.0f} deg "
        f"({optics.vibration_hz:g} Hz, decay {optics.vibration_damping_s:g} s)"
    )
    for effect, (Xe, _) in cells.items():
        d = Xe - Xe[:, -1:, :]
        rms = np.sqrt((d**2).mean(axis=0))
        print(
            f"  {effect:<9} capture - last, RMS (u, v) px: first {rms[0, 0]:.4f} {rms[0, 1]:.4f}, "
            f"second {rms[1, 0]:.4f} {rms[1, 1]:.4f}"
        )
    rs = np.linspace(0.2, 0.9, 15)
    ds = np.radians(np.arange(10, 181, 10))
    print("\ncost (px^2 x 1e4) of the vibration cell over the phase step (rows) and decay (cols)")
    print("Delta deg " + " ".join(f"{r:6.2f}" for r in rs[::2]))
    grid = np.array([[fit(X, r, d)[0] for r in rs] for d in ds])
    for d, row in zip(ds, grid, strict=True):
        print(f"{np.degrees(d):9.0f} " + " ".join(f"{c * 1e4:6.3f}" for c in row[::2]))
    i, j = np.unravel_index(grid.argmin(), grid.shape)
    at_truth = fit(X, r_true, d_true)[0]
    band = grid[(ds >= np.radians(30)) & (ds <= np.radians(150))][:, (rs >= 0.3) & (rs <= 0.7)]
    print(
        f"best Delta {np.degrees(ds[i]):.0f} deg, r {rs[j]:.2f}: {grid[i, j] * 1e4:.3f}; at the "
        f"truth {at_truth * 1e4:.3f}; over Delta 30-150 deg and r 0.3-0.7 "
        f"{band.min() * 1e4:.3f}-{band.max() * 1e4:.3f}"
    )
    from pipeline.stages.touchups.swing import moment_globals

    sigma2 = float(grid[i, j]) / len(X)  # one residual dof per touch-up
    got = moment_globals(X, sigma2, (float(rs[j]), float(ds[i])))
    if got is not None:
        print(
            f"pooled second moments (S2 of pipeline.stages.touchups.swing, noise "
            f"{np.sqrt(sigma2):.4f} px from the best cost): r {got[0]:.3f}, Delta "
            f"{np.degrees(got[1]):.0f} deg (what the touch-up stage uses)"
        )
    print("\nswing the fit at the truth's (r, Delta) puts into the last capture, RMS (u, v) px:")
    for effect, (Xe, _) in cells.items():
        swing = fit(Xe, r_true, d_true)[1]
        print(f"  {effect:<9} {np.sqrt((swing**2).mean(axis=0)).round(4)}")
    print("(on the still twin there is no swing: what the fit finds there is noise it would add)")
    print(f"total {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
