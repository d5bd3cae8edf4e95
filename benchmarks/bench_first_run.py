"""Benchmark: the first ``vtcal run`` after a fresh install against a warm run.

Builds a fresh virtual environment under ``--workdir`` (``python -m venv``, no
system site-packages) and installs vtcal into it in one of two ways (dependencies
from the configured indexes or the local wheel cache):

- ``--setup-line`` (what a new user does): ``git clone`` of this checkout's HEAD,
  then the README's set-up line exactly as written (read from README.md's
  "Set-up" section, run in the clone with the venv first on ``PATH``); the
  editable install compiles the detector into the clone (``setup.py``), and the
  runs below are the README's main command, run in the clone;
- default: ``pip install`` of this checkout (the build compiles the detector into
  the wheel, ``setup.py``), runs from a scratch folder (so no checkout is imported);

then, as fresh processes of the venv's own ``vtcal``:

1. the first ``vtcal run`` of the shipped sample, with an empty cache home
   (``XDG_CACHE_HOME``: vtcal's code-key and template caches, numba's user
   cache) and no ``NUMBA_CACHE_DIR``: what a new user waits for;
2. ``--repeat`` warm runs of the same recording into new folders (``--force``),
   the same cache home now filled: their median;

and prints the install time, both run times and their ratio (goal <= 1.5), the
ingest stage's seconds of each (``run.json``), whether the first run
announced a compile, and which of the first run's tables (``detections.parquet`` and every
other) differ from the warm run's (``pandas.DataFrame.equals``). ``--no-precompile`` installs
with ``VTCAL_NO_PRECOMPILE=1`` (the package without its compiled detector: the
state before), for the comparison. The load average is printed before and after.

    python benchmarks/bench_first_run.py [--setup-line] [--workdir /tmp/first_run] [--repeat 3]
                                         [--no-precompile]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"


def load() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def clean_env(cache_home: Path) -> dict[str, str]:
    """The environment of a new user: no checkout on the path, an empty cache home."""
    e = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    e["XDG_CACHE_HOME"] = str(cache_home)
    return e


def readme_setup_line() -> str:
    """The README's set-up line: the first indented command of its "Set-up" section."""
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.startswith("## Set-up")), None)
    for ln in lines[start + 1 :] if start is not None else []:
        if ln.startswith("## "):
            break
        if ln.startswith("    ") and ln.strip():
            return ln.strip()
    raise SystemExit("README.md: no indented command under a '## Set-up' heading")


def install_setup_line(venv: Path, clone: Path, precompile: bool) -> tuple[str, float]:
    """A fresh clone of HEAD and a fresh venv, then the README's set-up line in the clone.

    Returns the line and the seconds it took.
    """
    for d in (venv, clone):
        if d.exists():
            shutil.rmtree(d)
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)
    if not precompile:
        env["VTCAL_NO_PRECOMPILE"] = "1"
    line = readme_setup_line()
    t0 = time.perf_counter()
    proc = subprocess.run(["bash", "-c", line], cwd=clone, env=env, capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"{line!r} failed: {proc.stderr[-2000:]}")
    return line, took


def install(venv: Path, precompile: bool) -> float:
    """A fresh venv with this checkout installed; seconds of the ``pip install``."""
    if venv.exists():
        shutil.rmtree(venv)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    if not precompile:
        env["VTCAL_NO_PRECOMPILE"] = "1"
    t0 = time.perf_counter()
    proc = subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(ROOT)],
        env=env,
        capture_output=True,
        text=True,
    )
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"pip install failed: {proc.stderr[-2000:]}")
    return took


def run(venv: Path, out: Path, cache_home: Path, scratch: Path) -> tuple[float, str]:
    """Wall time and output (stdout and stderr) of one ``vtcal run SAMPLE --out OUT --force``.

    ``scratch`` is the working folder; the sample is read from it when it is a clone.
    """
    sample = scratch / SAMPLE.relative_to(ROOT)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            str(venv / "bin" / "vtcal"),
            "run",
            str(sample if sample.exists() else SAMPLE),
            "--out",
            str(out),
            "--force",
        ],  # fmt: skip
        env=clean_env(cache_home),
        cwd=scratch,
        capture_output=True,
        text=True,
    )
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"vtcal run failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return took, proc.stdout + proc.stderr


def ingest_seconds(out: Path) -> float:
    run_json = json.loads((out / "run.json").read_text())
    return next(float(s["seconds"]) for s in run_json["stages"] if s["stage"] == "ingest")


def differing_tables(a: Path, b: Path) -> list[str]:
    """The Parquet tables of run ``a`` whose values differ from run ``b``'s (not metadata)."""
    import pandas as pd

    files = sorted(p.name for p in a.glob("*.parquet"))
    assert "detections.parquet" in files, files
    return [f for f in files if not pd.read_parquet(a / f).equals(pd.read_parquet(b / f))]


def write_readme(first: float, warm: float) -> None:
    """README.md's ``<!-- first-run -->`` block: the figures this run measured."""
    readme = ROOT / "README.md"
    line = (
        f"first run of the sample {first:.1f} s, warm runs {warm:.1f} s (x{first / warm:.2f}; "
        "`benchmarks/bench_first_run.py --setup-line`, a fresh clone and venv)"
    )
    text, n = re.subn(
        r"(<!-- first-run -->\n).*?(\n<!-- /first-run -->)",
        lambda m: m.group(1) + line + m.group(2),
        readme.read_text(),
        flags=re.S,
    )
    if n != 1:
        raise SystemExit("README.md: no <!-- first-run --> block")
    readme.write_text(text)
    print(f"written: {readme}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None, help="venv and runs (under /tmp)")
    ap.add_argument("--repeat", type=int, default=3, help="warm runs")
    ap.add_argument(
        "--no-precompile", action="store_true", help="install without the compiled detector"
    )
    ap.add_argument(
        "--write",
        action="store_true",
        help="with --setup-line: write the figures into README.md's first-run block",
    )
    ap.add_argument(
        "--setup-line",
        action="store_true",
        help="a fresh clone, then the README's set-up line in it (what a new user does)",
    )
    args = ap.parse_args()
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_first_run_")
        workdir = Path(tmp.name)
    else:
        workdir = args.workdir
        shutil.rmtree(workdir, ignore_errors=True)
        workdir.mkdir(parents=True)
    print(f"load before: {load()}  (cores: {os.cpu_count()})", flush=True)
    venv, cache_home, scratch = workdir / "venv", workdir / "cache", workdir / "scratch"
    if args.setup_line:
        scratch = workdir / "clone"
        line, took = install_setup_line(venv, scratch, precompile=not args.no_precompile)
        print(
            f"fresh clone, then the README's set-up line {line!r} in a fresh venv ("
            f"{'without' if args.no_precompile else 'with'} the detector precompiled): "
            f"{took:.1f} s",
            flush=True,
        )
    else:
        scratch.mkdir()
        took = install(venv, precompile=not args.no_precompile)
        print(
            f"pip install of {ROOT.name} into a fresh venv ("
            f"{'without' if args.no_precompile else 'with'} the detector precompiled): "
            f"{took:.1f} s",
            flush=True,
        )
    first, said = run(venv, workdir / "run_first", cache_home, scratch)
    announced = "compiling the detector" in said
    warm = []
    for i in range(args.repeat):
        warm.append(run(venv, workdir / f"run_warm{i}", cache_home, scratch)[0])
    w = statistics.median(warm)
    print(
        f"first vtcal run after the install: {first:.2f} s (ingest "
        f"{ingest_seconds(workdir / 'run_first'):.2f} s; compile announced: {announced})\n"
        f"warm runs: median {w:.2f} s (ingest {ingest_seconds(workdir / 'run_warm0'):.2f} s), "
        f"{[round(x, 2) for x in warm]}\n"
        f"first / warm: {first / w:.2f} (goal <= 1.5: {'met' if first / w <= 1.5 else 'NOT met'})\n"
        f"tables of the first run that differ from the warm run's (detections.parquet and "
        f"every other): {differing_tables(workdir / 'run_first', workdir / 'run_warm0') or 'none'}"
    )
    print(f"load after: {load()}")
    if args.write and args.setup_line:
        write_readme(first, w)
    if tmp is not None:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
