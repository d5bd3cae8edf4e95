"""The live loop against the offline pipeline with every optical effect on.

For the LR Mate-like cell (``standard.toml``) and the UR5e-like cell
(``ur.toml``), 3 targets x 12 poses with a calibration bar, every optical
effect of ``benchmarks/bench_optics.py``'s ``all`` row at once (sRGB, defocus,
uneven light and sheen, shot and read noise with PRNU, Bayer, JPEG q90,
out-of-round prints, vibration), one seed:

- ``offline``: the simulator records the cell with its own controller
  (``write_recording``, as bench_optics does) and ``vtcal run`` calibrates it;
- ``live``: ``vtcal cell-server`` serves the same cell (same seed: same robot,
  targets and poses) over TCP, ``vtcal measure`` touches up the scenario's
  plan with vtcal's loop (what ``vtcal calibrate`` does after planning) and
  ``vtcal run`` calibrates the recording; the cell's ``META?`` says its
  ``camera_response`` (when the code knows the key);
- ``live, undeclared``: the same, the server withholding ``camera_response``
  (``--withhold camera_response``): the live loop estimates the response from
  its first clean captures.

Printed per row: shape and absolute RMS of the calibrated pin against the
truth (mm, 500 poses, ``pipeline.accuracy.evaluate.judge_run``), the nominal robot's
shape RMS, the response the run used, how many touch-ups converged, and the
loop's stopping size in the offline detector's measure (``e_s_px`` of the
touch-up table: mean and RMS over the touch-ups, px) beside the loop's
own measure of it (``loop e_s``: mean over converged touch-ups of the size error
the loop saw at its converging capture, from the progress file; within the
0.5 px threshold by construction). Their gap is what the loop's detector does
not share with the offline one (response, flat field, averaging of the repeats). ``--save`` keeps the figures as
JSON; ``--before`` prints a saved run (today's code) beside them.

    nice -n 10 python benchmarks/bench_live_offline.py --save new.json
    nice -n 10 python benchmarks/bench_live_offline.py --cells lrmate --rows live
    git stash; nice -n 10 python benchmarks/bench_live_offline.py --save today.json; git stash pop
    python benchmarks/bench_live_offline.py --show new.json --before today.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_optics import BINARY_CONTROLLER, CELLS, EFFECTS  # noqa: E402

ROWS = ("offline", "live", "live, undeclared")


def scenario_file(cell: str, effect: str, work: Path, controller: bool) -> tuple[Path, Any]:
    """The cell's scenario with ``effect``'s optics, as a TOML file and as a Scenario."""
    from pipeline.sim.scenario import scenario_from_dict

    raw = tomllib.loads((REPO / "datasets" / "scenarios" / CELLS[cell]).read_text())
    raw.setdefault("poses", {})["per_target"] = 12
    raw["optics"] = dict(EFFECTS[effect])
    if controller and effect in BINARY_CONTROLLER:
        raw.setdefault("touchup", {})["controller"] = "binary"
    path = work / f"{cell}_{effect.replace(' ', '_')}.toml"
    path.write_text(_toml(raw))
    return path, scenario_from_dict(raw, where=str(path), base_dir=str(REPO))


def _toml(raw: dict[str, Any]) -> str:
    """A flat two-level TOML writer (scenario files are tables of scalars and lists)."""

    def val(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)

    lines = [f"{k} = {val(v)}" for k, v in raw.items() if not isinstance(v, dict)]
    for k, v in raw.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {val(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def judge(rec: Path, truth: dict[str, Any], out: Path, seed: int) -> dict[str, Any]:
    """``vtcal run`` on ``rec`` and the calibrated pin against the truth."""
    from pipeline.accuracy.evaluate import judge_run
    from pipeline.io.artefacts import read_artefact
    from pipeline.run.orchestrator import RunConfig, run_pipeline

    t0 = time.perf_counter()
    run_pipeline(rec, out, RunConfig(report=False), until="crossval")
    t_run = time.perf_counter() - t0
    j = judge_run(out, truth, 500, seed)
    tu = read_artefact(out / "touchups.parquet", "touchups")
    conv = tu[tu["converged"].astype(bool)]
    es = tu["e_s_px"].to_numpy(dtype=float)
    es = es[np.isfinite(es)]
    cam = json.loads((out / "recording.json").read_text()).get("camera", {})
    return {
        "shape": j["after"]["shape_rms_m"] * 1e3,
        "abs": j["after"]["abs_rms_m"] * 1e3,
        "nominal": j["before"]["shape_rms_m"] * 1e3,
        "response": f"{cam.get('response', '?')} ({cam.get('response_source', '?')})",
        "converged": f"{len(conv)}/{len(tu)}",
        "es_mean": float(np.mean(es)) if len(es) else float("nan"),
        "es_rms": float(np.sqrt(np.mean(es**2))) if len(es) else float("nan"),
        "run_s": t_run,
    }


def offline(cell: str, effect: str, seed: int, work: Path) -> dict[str, Any]:
    from pipeline.sim.simulator import write_recording

    _, sc = scenario_file(cell, effect, work, controller=True)
    rec = work / f"{cell}_offline_{seed}.mcap"
    truth = write_recording(sc, seed, rec)
    return judge(rec, truth, work / f"{cell}_offline_{seed}", seed)


def live(cell: str, effect: str, seed: int, work: Path, withhold: bool) -> dict[str, Any]:
    from bench_measure import truth_of

    from pipeline.commands.measure import run_measure
    from pipeline.errors import CellFault

    path, _ = scenario_file(cell, effect, work, controller=False)
    tag = f"{cell}_live{'_undeclared' if withhold else ''}_{seed}"
    plan = work / f"{tag}_plan.parquet"
    cmd = [sys.executable, "-m", "pipeline", "cell-server", "--scenario", str(path),
           "--seed", str(seed), "--port", "0", "--plan-out", str(plan)]  # fmt: skip
    if withhold:
        cmd += ["--withhold", "camera_response"]
    server = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        assert server.stderr is not None
        line = server.stderr.readline()
        if not line.startswith("vtcal cell-server:"):
            return {"error": (line + server.stderr.read()).strip().splitlines()[-1]}
        url = line.split()[2]
        rec = work / f"{tag}.mcap"
        t0 = time.perf_counter()
        for _attempt in range(3):  # a loaded machine can starve the server past a timeout
            try:
                run_measure(plan, url, None, rec, None, {}, 0.5, 12, 0.9, 0.0, True)
                break
            except CellFault as exc:
                print(f"# {tag}: {exc} (resuming)", flush=True)
        t_meas = time.perf_counter() - t0
    finally:
        server.terminate()
        server.wait()
    truth = truth_of(f"sim:{path}:{seed}")  # the same cell (scenario and seed)
    prog = json.loads(rec.with_name(rec.name + ".progress.json").read_text())
    es_loop = [t["final_error_px"][2] for t in prog["touchups"] if t["converged"]]
    return {
        **judge(rec, truth, work / f"{tag}_run", seed),
        "measure_s": t_meas,
        "es_loop": float(np.mean(es_loop)) if es_loop else float("nan"),
    }


def show(res: dict[str, Any], before: dict[str, Any] | None) -> None:
    """Per (cell, row, seed) the figures, today's (``before``) under them; then the means."""
    print(
        f"{'cell':7s} {'row':17s} {'seed':>4s} {'shape mm':>8s} {'abs mm':>7s} {'nominal':>7s} "
        f"{'conv':>6s} {'e_s mean/rms px':>15s} {'loop e_s':>8s}  response"
    )
    both = {**(before or {}), **res}
    for key in sorted(both, key=lambda k: (k.split("|")[0], ROWS.index(k.split("|")[1]), k)):
        cell, row, seed = key.split("|")
        for tag, rr in (("", res.get(key)), ("  today", (before or {}).get(key))):
            if rr is None:
                continue
            name = f"{row}{tag}"
            if "error" in rr:
                print(f"{cell:7s} {name:17s} {seed:>4s} {rr['error']}")
                continue
            print(
                f"{cell:7s} {name:17s} {seed:>4s} {rr['shape']:8.3f} {rr['abs']:7.3f} "
                f"{rr['nominal']:7.2f} {rr['converged']:>6s} "
                f"{rr['es_mean']:+7.3f}/{rr['es_rms']:6.3f} "
                f"{rr.get('es_loop', float('nan')):+8.3f}  {rr['response']}"
            )
    print("means over seeds (shape / abs mm); ratio: live / offline over the seeds both have")
    for cell in sorted({k.split("|")[0] for k in both}):
        for row in ROWS:
            for tag, src in (("", res), (" today", before or {})):
                m = _rows(src, cell, row)
                if not m or (row == "offline" and tag):
                    continue
                line = (
                    f"  {cell:7s} {row + tag:23s} {np.mean([r['shape'] for r in m.values()]):.4f}"
                    f" / {np.mean([r['abs'] for r in m.values()]):.4f} (seeds {','.join(m)})"
                )
                off = _rows(both, cell, "offline")
                common = [sd for sd in m if sd in off]
                if row != "offline" and common:
                    ratio = [
                        np.mean([m[sd][k] for sd in common])
                        / np.mean([off[sd][k] for sd in common])
                        for k in ("shape", "abs")
                    ]
                    line += f"  {ratio[0]:.2f}x / {ratio[1]:.2f}x (seeds {','.join(common)})"
                print(line)


def _rows(res: dict[str, Any], cell: str, row: str) -> dict[str, dict[str, Any]]:
    """seed -> figures of (cell, row), runs that failed left out."""
    return {
        k.split("|")[2]: v
        for k, v in sorted(res.items())
        if k.split("|")[:2] == [cell, row] and "error" not in v
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", nargs="+", default=list(CELLS), choices=list(CELLS))
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--effect", default="all", choices=list(EFFECTS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[7])
    ap.add_argument("--save", type=Path, default=None)
    ap.add_argument("--before", type=Path, default=None, help="today's figures (a --save file)")
    ap.add_argument("--show", type=Path, default=None, help="print a --save file and stop")
    args = ap.parse_args()
    before = json.loads(args.before.read_text()) if args.before else None
    if args.show:
        show(json.loads(args.show.read_text()), before)
        return
    from pipeline.errors import BadInput, CellFault

    res: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for seed in args.seeds:
            for cell in args.cells:
                for row in args.rows:
                    t0 = time.perf_counter()
                    try:
                        if row == "offline":
                            r = offline(cell, args.effect, seed, work)
                        else:
                            r = live(cell, args.effect, seed, work, row == "live, undeclared")
                    except (BadInput, CellFault) as exc:  # the row failed; the others run
                        r = {"error": f"{type(exc).__name__}: {exc}"}
                    r["wall_s"] = time.perf_counter() - t0
                    res[f"{cell}|{row}|{seed}"] = r
                    print(f"# {cell} {row} {seed}: {json.dumps(r)}", flush=True)
                    if args.save:
                        args.save.write_text(json.dumps(res, indent=1) + "\n")
    print(f"effect {args.effect!r}, seeds {args.seeds}")
    show(res, before)


if __name__ == "__main__":
    main()
