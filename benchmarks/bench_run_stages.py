"""Benchmark: where the user waits in ``vtcal run`` (a single run).

Simulates the standard cells once (LR Mate-like ``standard.toml`` and UR5e-like
``ur.toml`` at 36 touch-ups, LR Mate-like at 72; seed 7, into ``--workdir``,
reused when already there), then measures in this one run:

1. ``vtcal run REC --out DIR --force -q`` as a fresh process, ``--repeat`` times
   per cell: per-stage wall time from ``run.json`` (median over the repeats),
   the ingest time and the ratio (everything after ingest) / ingest
   (goal <= 0.5) and the report stage (goal < 0.5 s); and, interleaved with
   those runs (a fresh process each, its imports not timed), the read floor:
   the stock readers (``mcap`` + ``mcap_ros2``) reading the same file and
   decoding every message (images to pixels, joint states), with the ratios
   whole run (the stages' seconds) / floor (goal <= 1.5), ingest /
   floor and the process's wall time / floor;
2. the report stage (``pipeline.report.outputs.build_outputs``) in this process
   with warm imports, and its cProfile on the first cell's run folder, top
   ``--top`` functions by cumulative time;
3. start-up, as fresh processes, median of ``--repeat-startup`` (5): ``vtcal
   --help`` (goal < 0.3 s), a cached ``vtcal run`` of the first cell (goal
   < 0.5 s), ``vtcal report`` of it; and the heaviest imports of each from
   ``python -X importtime``;
4. ``--first-run``: the shipped sample's ``vtcal run`` in a fresh process with
   the detector's compiled cache removed (first run after a fresh install)
   against the same run warm (compiled cache present), both ``--force``.

The machine's load average is printed before and after: timings on a shared
machine are noisy, medians are what to compare.

    python benchmarks/bench_run_stages.py [--workdir DIR] [--repeat 3] [--first-run]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"
#: (label, scenario file, poses per target): 3 targets each
CELLS = (
    ("lrmate-36", "standard.toml", 12),
    ("ur5e-36", "ur.toml", 12),
    ("lrmate-72", "standard.toml", 24),
)
SEED = 7


def env() -> dict[str, str]:
    """Environment of the child processes: this checkout first on the path."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    return e


def load() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def simulate(workdir: Path) -> dict[str, Path]:
    """The cells' recordings, simulated when not in ``workdir`` yet."""
    from pipeline.sim.scenario import scenario_from_dict
    from pipeline.sim.simulator import write_recording

    recs = {}
    for label, scenario, per_target in CELLS:
        rec = workdir / f"{label}_s{SEED}.mcap"
        if not rec.exists():
            raw = tomllib.loads((ROOT / "datasets" / "scenarios" / scenario).read_text())
            raw.setdefault("poses", {})["per_target"] = per_target
            sc = scenario_from_dict(raw, where=label, base_dir=str(ROOT))
            t0 = time.perf_counter()
            write_recording(sc, SEED, rec)
            print(f"simulated {label}: {time.perf_counter() - t0:.1f} s", flush=True)
        recs[label] = rec
    return recs


def children_cpu() -> float:
    """CPU seconds (user + system) of this process's waited-for children and theirs."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def vtcal_cpu(*args: str) -> tuple[float, float]:
    """Wall time and CPU time (its whole process tree) of one ``python -m pipeline ARGS``."""
    t0, c0 = time.perf_counter(), children_cpu()
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", *args], env=env(), capture_output=True, text=True
    )
    took, cpu = time.perf_counter() - t0, children_cpu() - c0
    if proc.returncode != 0:
        raise SystemExit(f"vtcal {' '.join(args)} failed ({proc.returncode}): {proc.stderr}")
    return took, cpu


def vtcal(*args: str) -> float:
    """Wall time of one ``python -m pipeline ARGS`` process (it must succeed)."""
    return vtcal_cpu(*args)[0]


def read_floor(path: Path) -> tuple[float, float]:
    """Seconds the stock readers take to read ``path`` and decode every message.

    ``mcap_ros2``'s ``iter_decoded_messages`` decodes each message (joint states,
    images, the rest); an image's pixels are then made an array (raw: the buffer
    reshaped; compressed: ``cv2.imdecode``). Imports are not timed. Returns the wall
    and the CPU seconds.
    """
    import cv2
    import numpy as np
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    t0, c0 = time.perf_counter(), time.process_time()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, _, _, msg in reader.iter_decoded_messages(log_time_order=False):
            name = schema.name if schema is not None else ""
            if name.endswith("CompressedImage"):
                cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
            elif name.endswith("/Image"):
                np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)
    return time.perf_counter() - t0, time.process_time() - c0


def floor_process(rec: Path) -> tuple[float, float]:
    """:func:`read_floor` of ``rec`` in a fresh process (as the runs are): wall, CPU."""
    proc = subprocess.run(
        [sys.executable, __file__, "--floor", str(rec)], env=env(), capture_output=True, text=True
    )
    if proc.returncode != 0:
        raise SystemExit(f"read floor of {rec} failed: {proc.stderr}")
    wall, cpu = proc.stdout.split()[-2:]
    return float(wall), float(cpu)


def stage_seconds(out: Path) -> dict[str, float]:
    """``{stage: seconds}`` of the stages that ran, from ``run.json``."""
    run = json.loads((out / "run.json").read_text())
    return {s["stage"]: float(s["seconds"]) for s in run["stages"] if s["status"] == "ran"}


def bench_stages(recs: dict[str, Path], workdir: Path, repeat: int) -> None:
    """Per-stage wall time of ``vtcal run --force`` per cell, median over ``repeat`` runs."""
    print(f"\n== vtcal run --force, fresh process, median of {repeat} (load {load()})")
    from pipeline.run.catalog import STAGES

    # every stage the runner declares (the choose stage included), then the report
    names = tuple(dict.fromkeys([*(st.name for st in STAGES), "report"]))
    print(
        f"{'cell':<10}" + "".join(f"{n:>9}" for n in names) + f"{'after':>8}{'after/ingest':>13}"
        f"{'wall':>7}"
    )
    floors: dict[str, tuple[float, ...]] = {}
    for label, rec in recs.items():
        out = workdir / f"run_{label}"
        per: dict[str, list[float]] = {n: [] for n in names}
        per.setdefault("report", [])
        walls, floor, whole, cpus, floor_cpu = [], [], [], [], []
        for _ in range(repeat):
            wall, cpu = vtcal_cpu("run", str(rec), "--out", str(out), "--force", "-q")
            walls.append(wall)
            cpus.append(cpu)
            secs = stage_seconds(out)
            whole.append(sum(secs.values()))
            for n, s in secs.items():
                per.setdefault(n, []).append(s)
            fw, fc = floor_process(rec)
            floor.append(fw)
            floor_cpu.append(fc)
        med = {n: statistics.median(v) for n, v in per.items() if v}
        after = sum(v for n, v in med.items() if n != "ingest")
        floors[label] = (
            statistics.median(floor),
            statistics.median(whole),
            med["ingest"],
            statistics.median(walls),
            statistics.median(floor_cpu),
            statistics.median(cpus),
        )
        print(
            f"{label:<10}"
            + "".join(f"{med.get(n, float('nan')):9.3f}" for n in names)
            + f"{after:8.3f}{after / med['ingest']:13.2f}{statistics.median(walls):7.2f}"
        )
    print("goals: after/ingest <= 0.5, report < 0.5 s")
    print(
        f"\n== the read floor: stock mcap + mcap_ros2 read and decode of the same file, fresh "
        f"process, median of {repeat}, interleaved with the runs (load {load()})"
    )
    print(
        f"{'cell':<10}{'floor':>8}{'whole run':>11}{'ingest':>8}{'run/floor':>11}"
        f"{'ingest/floor':>14}{'wall/floor':>12}{'floor CPU':>11}{'run CPU':>9}"
    )
    for label, (fl, wh, ing, wall, fcpu, rcpu) in floors.items():
        print(
            f"{label:<10}{fl:8.3f}{wh:11.3f}{ing:8.3f}{wh / fl:11.2f}{ing / fl:14.2f}"
            f"{wall / fl:12.2f}{fcpu:11.3f}{rcpu:9.3f}"
        )
    print(
        "goal: whole run (the stages' seconds) / floor <= 1.5. CPU: the floor's "
        "read+decode, and the run's whole process tree (imports, the warm report process, "
        "forked fits: it counts both cores)"
    )


def profile_report(out: Path, top: int) -> None:
    """cProfile of the report stage on one run folder: top functions by cumulative time."""
    from pipeline.report.outputs import build_outputs

    build_outputs(out)  # imports and first-call costs out of the profile
    t0 = time.perf_counter()
    build_outputs(out)
    t1 = time.perf_counter()
    if top <= 0:
        print(f"\n== report stage in process (warm imports): report.html + run.rrd {t1 - t0:.3f} s")
        return
    prof = cProfile.Profile()
    prof.enable()
    build_outputs(out)
    prof.disable()
    print(
        f"\n== report stage in process (warm imports): report.html + run.rrd {t1 - t0:.3f} s; "
        "profiled:"
    )
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(top)
    lines = s.getvalue().splitlines()
    start = next(i for i, line in enumerate(lines) if "ncalls" in line)
    print("\n".join(line[:150] for line in lines[start : start + top + 1]))


def importtime(*args: str, top: int = 6) -> str:
    """The ``top`` heaviest imports (cumulative us) of ``python -X importtime -m pipeline ARGS``."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "pipeline", *args],
        env=env(),
        capture_output=True,
        text=True,
    )
    rows = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, cum_us, name = line[len("import time:") :].split("|")
        rows.append((int(cum_us), name.rstrip()))
    indent = min(len(n) - len(n.lstrip()) for _, n in rows)
    total = sum(c for c, n in rows if len(n) - len(n.lstrip()) == indent)
    heavy = sorted(rows, reverse=True)[:top]
    return f"imports {total / 1e6:.3f} s; heaviest: " + ", ".join(
        f"{n.strip()} {c / 1e6:.3f}" for c, n in heavy
    )


def bench_startup(rec: Path, out: Path, repeat: int) -> None:
    """Fresh-process wall time of --help, a cached run and vtcal report (median of ``repeat``)."""
    print(f"\n== start-up, fresh process, median of {repeat} (load {load()})")
    vtcal("run", str(rec), "--out", str(out), "-q")  # make sure the ledger vouches for it
    cases = {
        "vtcal --help": (("--help",), 0.3),
        "cached vtcal run": (("run", str(rec), "--out", str(out), "-q"), 0.5),
        "vtcal report": (("report", str(out)), None),
    }
    for name, (args, goal) in cases.items():
        times = [vtcal(*args) for _ in range(repeat)]
        med = statistics.median(times)
        verdict = "" if goal is None else f"  goal < {goal} s: {'met' if med < goal else 'NOT met'}"
        print(
            f"{name:<18} median {med:.3f} s (min {min(times):.3f}, max {max(times):.3f}){verdict}"
        )
        print(f"{'':<18} {importtime(*args)}")


def jit_cache_files() -> list[Path]:
    """The compiled-code cache files (numba ``cache=True``) of the detector and the edge fit.

    Beside each module in ``__pycache__`` (``_jit.*.nbi`` index, ``*.nbc`` code),
    or under ``NUMBA_CACHE_DIR`` when that is set.
    """
    import importlib.util

    found = []
    for module in ("pipeline.stages.detect._jit", "pipeline.stages.response._edge_jit"):
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin is not None
        stem = module.rsplit(".", 1)[1]
        found += [*(Path(spec.origin).parent / "__pycache__").glob(f"{stem}.*.nb[ic]")]
        if os.environ.get("NUMBA_CACHE_DIR"):
            found += [*Path(os.environ["NUMBA_CACHE_DIR"]).rglob(f"{stem}.*.nb[ic]")]
    return found


def bench_first_run(workdir: Path, repeat: int) -> None:
    """The sample's run with the compiled cache removed vs warm (fresh processes, --force)."""
    out = workdir / "run_sample"
    print(f"\n== first run vs warm run of the sample, fresh process (load {load()})")
    cold, cold_compile, warm = [], [], []
    for _ in range(repeat):
        for p in jit_cache_files():
            p.unlink()
        cold.append(vtcal("run", str(SAMPLE), "--out", str(out), "--force", "-q"))
        cold_compile.append(stage_seconds(out).get("ingest", float("nan")))
        warm.append(vtcal("run", str(SAMPLE), "--out", str(out), "--force", "-q"))
    c, w = statistics.median(cold), statistics.median(warm)
    print(
        f"first run (no compiled cache) median {c:.2f} s (ingest stage "
        f"{statistics.median(cold_compile):.2f} s); warm run {w:.2f} s; ratio {c / w:.2f} "
        f"(goal <= 1.5 or announced with progress); runs: cold {[round(x, 2) for x in cold]}, "
        f"warm {[round(x, 2) for x in warm]}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None, help="keep recordings and runs here")
    ap.add_argument("--repeat", type=int, default=3, help="vtcal run repeats per cell")
    ap.add_argument("--repeat-startup", type=int, default=5)
    ap.add_argument("--top", type=int, default=25, help="profile rows")
    ap.add_argument("--first-run", action="store_true", help="also time a first run (cold JIT)")
    ap.add_argument("--only", default=None, help="one cell label (e.g. lrmate-36)")
    ap.add_argument("--floor", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--skip-startup", action="store_true", help="no report profile, start-up")
    args = ap.parse_args()
    if args.floor is not None:  # the child of floor_process
        print("{:.6f} {:.6f}".format(*read_floor(args.floor)))
        return
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_run_stages_")
        workdir = Path(tmp.name)
    else:
        workdir = args.workdir
        workdir.mkdir(parents=True, exist_ok=True)
    print(f"load before: {load()}  (cores: {os.cpu_count()})")
    recs = simulate(workdir)
    if args.only:
        recs = {args.only: recs[args.only]}
    bench_stages(recs, workdir, args.repeat)
    first = next(iter(recs))
    if not args.skip_startup:
        profile_report(workdir / f"run_{first}", args.top)
        bench_startup(recs[first], workdir / f"run_{first}", args.repeat_startup)
    if args.first_run:
        bench_first_run(workdir, 1 if args.repeat < 2 else 2)
    print(f"\nload after: {load()}")
    if tmp is not None:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
