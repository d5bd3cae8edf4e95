"""The stages after ingest, this checkout against another, in alternating fresh processes.

``bench_run_stages.py`` times whole runs of one checkout; on a shared 2-core
machine two of its runs a minute apart differ by more than a change to the
stages after ingest saves: whether the warm report process starts and whether
identification and cross-validation fork both follow the load at that moment
(``pipeline/report/warm.py``, ``pipeline/stages/parallel_map.py``). This script
compares two checkouts doing the same work the same way: every round runs each
checkout once per cell (alternating which goes first), in a fresh process whose
ingest is cached (its imports made first, as ingest makes them), the later
stages' outputs removed, the fits in one process (``--workers``, default 1) and
the report built in-process (``--warm`` starts the warm report process as a run
would). It prints each stage's seconds (``run.json``'s), min and median over
``--repeat`` rounds, and the load.

    python benchmarks/bench_run_stages.py --workdir /tmp/brs --repeat 1   # the recordings
    python benchmarks/bench_stages_ab.py --workdir /tmp/brs --other /path/to/main
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ["touchups", "outliers", "identify", "crossval", "choose", "report"]
CELLS = ["lrmate-36", "ur5e-36", "lrmate-72"]

#: the child: ingest's imports, then the run with ingest cached and the rest made again
CHILD = r"""
import json, sys
from pathlib import Path
import numpy, pandas, pyarrow.parquet
import pipeline.stages.ingest.stage, pipeline.stages.detect.detector
from pipeline.run.orchestrator import RunConfig, run_pipeline
rec, out, workers = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
keep = {"frames.parquet", "detections.parquet", "recording.json"}
for p in out.iterdir():
    if p.is_file() and p.name not in keep:
        p.unlink()
opts = {"identify": {"workers": workers}, "crossval": {"workers": workers}}
res = run_pipeline(rec, out, RunConfig(stage_options=opts))
print(json.dumps({s.stage: s.seconds for s in res.stages}))
"""


def run_once(tree: Path, rec: Path, out: Path, workers: int, warm: bool) -> dict[str, float]:
    """One fresh process of checkout ``tree``: its stage seconds."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    if not warm:
        env["VTCAL_WARM_REPORT"] = "0"
    if not (out / "frames.parquet").exists():  # ingest once per checkout and cell
        shutil.rmtree(out, ignore_errors=True)
        subprocess.run(
            [sys.executable, "-m", "pipeline", "run", str(rec), "--out", str(out), "-q"],
            env=env,
            cwd=tree,  # "-m"/"-c" put the working folder first on the path
            check=True,
            capture_output=True,
        )
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(rec), str(out), str(workers)],
        env=env,
        cwd=tree,
        check=True,
        capture_output=True,
        text=True,
    )
    seconds: dict[str, float] = json.loads(proc.stdout.strip().splitlines()[-1])
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", type=Path, required=True, help="bench_run_stages.py's workdir")
    ap.add_argument("--other", type=Path, required=True, help="the checkout to compare with")
    ap.add_argument("--cells", default=",".join(CELLS))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--workers", type=int, default=1, help="identify/crossval processes")
    ap.add_argument("--warm", action="store_true", help="let the warm report process start")
    args = ap.parse_args()
    trees = {"other": args.other.resolve(), "this": ROOT}
    args.workdir = args.workdir.resolve()
    cells = args.cells.split(",")
    got: dict[tuple[str, str], list[dict[str, float]]] = {(t, c): [] for t in trees for c in cells}
    loads = [os.getloadavg()[0]]
    for r in range(args.repeat):
        order = list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]
        for cell in cells:
            rec = args.workdir / f"{cell}_s7.mcap"
            for name, tree in order:
                out = args.workdir / f"ab_{name}_{cell}"
                got[(name, cell)].append(run_once(tree, rec, out, args.workers, args.warm))
        loads.append(os.getloadavg()[0])
    print(
        f"stages after ingest, {args.repeat} alternating rounds, workers {args.workers}, "
        f"warm report {'on' if args.warm else 'off'}; 1-min load {min(loads):.2f}-{max(loads):.2f}"
    )
    print(f"  other = {trees['other']}, this = {trees['this']}")
    print(f"{'cell':10s} {'tree':5s} {'':6s} " + " ".join(f"{s:>8s}" for s in STAGES) + "    after")
    for cell in cells:
        for name in trees:
            runs = got[(name, cell)]
            for agg in (min, statistics.median):
                vals = [agg(x.get(s, 0.0) for x in runs) for s in STAGES]
                after = agg(sum(x.get(s, 0.0) for s in STAGES) for x in runs)
                print(
                    f"{cell:10s} {name:5s} {agg.__name__:6s} "
                    + " ".join(f"{v:8.3f}" for v in vals)
                    + f"  {after:7.3f}"
                )


if __name__ == "__main__":
    main()
