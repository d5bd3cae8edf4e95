"""Benchmark: are a run's artefacts the same as before a refactor?

A refactor of the runner changes the shape of the code, not its results. This
script makes three run folders and prints one SHA-256 per artefact:

1. ``vtcal run`` on the shipped sample (``datasets/samples/sample_lrmate.mcap``,
   copied into ``--workdir``: ``recording.json`` names its path, which is then
   the same for two checkouts);
2. ``vtcal run`` on the standard cell (``datasets/scenarios/standard.toml``,
   seed 7: 3 targets x 12 poses), simulated once into ``--workdir`` and reused
   (so a change of the simulator does not count against the runner);
3. ``vtcal identify`` on the sample run's ``touchups.parquet`` with the URDF
   its ``recording.json`` holds (the table entry point of the same runner);
   the table is copied into ``--workdir`` once and reused (its bytes, named in
   the provenance block, hold the touch-up stage's code digest).

What is hashed, and what is masked (fields that legitimately change when code
moves or that are timings):

* Parquet files: the table data (serialised as Arrow IPC; equal digests =
  ``Table.equals``) and, apart, the ``vtcal.*`` schema metadata with ``vtcal.config_hash`` (it holds the stage code digest) and
  ``vtcal.inputs`` (hashes of input *files*, whose metadata holds that digest)
  masked.
* ``identify.json`` and ``models.json``: every key named ``seconds`` (fit wall
  time) dropped.
* ``run.json``: ``stages[*].seconds`` dropped; ``report_inputs`` and the
  ledger's artefact hashes and code digest reduced to their key sets (they hash
  files whose metadata holds code digests).
* ``report.html``: the ``seconds`` of the embedded identify.json, the
  seconds column of the stage table, the 16-hex-digit artefact hashes and the
  run id (a UUID from those hashes) masked.
* ``run.rrd``: read back with rerun's ``RrdReader``: every chunk's entity
  path and columns are hashed, but not its row ids (rerun stamps them with
  the wall clock) nor the recording id (the run id, a hash of the artefacts'
  bytes, so of the fit timings and code digests above).
* ``calibrated*.urdf``: the provenance block's ``run id`` masked (a hash of
  the run request, which holds a digest of every package file), and its source
  file's hash (a touch-up table's metadata holds the stage code digest).
* Every other file (``recording.json``) byte for byte.

    python benchmarks/bench_artefacts_identity.py --save before.json
    python benchmarks/bench_artefacts_identity.py --check before.json

``--check`` prints, per case and file, ``same`` or ``DIFFERS`` and exits 1 when
any differs. The wall time of each case is printed too (one run each).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"
SCENARIO = ROOT / "datasets" / "scenarios" / "standard.toml"
SEED = 7
MASKED_META = (b"vtcal.config_hash", b"vtcal.inputs")


def env() -> dict[str, str]:
    """Environment of the child processes: this checkout first on the path."""
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    return e


def vtcal(*args: str) -> float:
    """Run ``vtcal ARGS`` in a fresh process; its wall time (s). Exits on failure."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", *args], env=env(), capture_output=True, text=True
    )
    if proc.returncode not in (0, 1):  # 1: a FAIL verdict is still a finished run
        sys.exit(f"vtcal {' '.join(args)} exited {proc.returncode}: {proc.stderr.strip()}")
    return time.perf_counter() - t0


def parquet_digest(path: Path) -> str:
    """``DATA/META``: SHA-256 (32 hex each) of a Parquet file's table data and of its
    ``vtcal.*`` metadata with the masked keys left out."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    meta = dict(table.schema.metadata or {})
    schema = table.schema.remove_metadata()
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_table(table.replace_schema_metadata(None))
    h = hashlib.sha256()
    for key in sorted(meta):
        if key.startswith(b"vtcal.") and key not in MASKED_META:
            h.update(key + b"\0" + meta[key] + b"\0")
    return hashlib.sha256(sink.getvalue()).hexdigest()[:32] + "/" + h.hexdigest()[:32]


def _drop_seconds(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop_seconds(v) for k, v in obj.items() if k != "seconds"}
    if isinstance(obj, list):
        return [_drop_seconds(v) for v in obj]
    return obj


def run_json_view(obj: dict[str, Any]) -> dict[str, Any]:
    """run.json without timings and with the code-bearing hashes reduced to key sets."""
    out = _drop_seconds(obj)
    if isinstance(out.get("report_inputs"), dict):
        out["report_inputs"] = sorted(out["report_inputs"])
    ledger = out.get("ledger")
    if isinstance(ledger, dict):
        ledger["artefacts"] = sorted(ledger.get("artefacts", {}))
        ledger.get("fingerprint", {}).pop("code", None)
    return out


def html_view(text: str) -> str:
    """report.html without the fit timings and the stage table's seconds column."""
    text = re.sub(r"seconds&#34;: [0-9.eE+-]+", "seconds&#34;: X", text)
    text = re.sub(r"<code>[0-9a-f]{16}</code>", "<code>HASH</code>", text)
    text = re.sub(r"Run id [0-9a-f-]{36}", "Run id X", text)
    return re.sub(
        r"(<td>(?:ran|cached|skipped)</td>)<td class=\"num\">[0-9.]+</td>", r"\1<td>X</td>", text
    )


def rrd_digest(path: Path) -> str:
    """SHA-256 of what ``run.rrd`` holds: every chunk's entity and columns, row ids left out."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream().to_chunks():
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if "RowId" not in n}
        rows.append(repr((chunk.entity_path, sorted(cols.items()))))
    return hashlib.sha256("\n".join(sorted(rows)).encode()).hexdigest()


def digest(path: Path) -> str:
    """The compared digest of one run-folder file (see the module docstring)."""
    if path.suffix == ".parquet":
        return parquet_digest(path)
    if path.name in ("identify.json", "models.json"):
        blob = json.dumps(_drop_seconds(json.loads(path.read_text())), sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()
    if path.name == "run.json":
        blob = json.dumps(run_json_view(json.loads(path.read_text())), sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()
    if path.suffix == ".urdf":
        text = re.sub(r"run id: [0-9a-f]+", "run id: X", path.read_text())
        # a touch-up table's hash: its file's metadata holds the stage code digest
        text = re.sub(r"sha256 \(first 16 hex\) [0-9a-f]+", "sha256 X", text)
        return hashlib.sha256(text.encode()).hexdigest()
    if path.name == "run.rrd":
        return rrd_digest(path)
    if path.name == "report.html":
        return hashlib.sha256(html_view(path.read_text()).encode()).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def folder_digests(run: Path) -> dict[str, str]:
    """``{file name: digest}`` of every file of a run folder."""
    return {p.name: digest(p) for p in sorted(run.iterdir()) if p.is_file()}


def make_runs(workdir: Path) -> tuple[dict[str, Path], dict[str, float]]:
    """The three run folders (module docstring), made afresh; and each case's wall time."""
    import shutil

    workdir.mkdir(parents=True, exist_ok=True)
    rec = workdir / f"standard_s{SEED}.mcap"
    if not rec.exists():
        vtcal("simulate", "--scenario", str(SCENARIO), "--seed", str(SEED), "--out", str(rec))
    sample = workdir / SAMPLE.name
    if not sample.exists():
        shutil.copyfile(SAMPLE, sample)
    runs = {"sample": workdir / "sample_run", "standard": workdir / "standard_run"}
    runs["identify"] = workdir / "identify_out"
    for d in runs.values():
        shutil.rmtree(d, ignore_errors=True)
    wall = {
        "sample": vtcal("run", str(sample), "--out", str(runs["sample"]), "-q"),
        "standard": vtcal("run", str(rec), "--out", str(runs["standard"]), "-q"),
    }
    info = json.loads((runs["sample"] / "recording.json").read_text())
    urdf = workdir / "sample_robot.urdf"
    urdf.write_text(info["urdf"])
    table = workdir / "touchups.parquet"
    if not table.exists():
        shutil.copyfile(runs["sample"] / "touchups.parquet", table)
    wall["identify"] = vtcal(
        "identify",
        str(table),
        "--urdf",
        str(urdf),
        "--out",
        str(runs["identify"]),
        "--base-link",
        info["base_link"],
        "--flange-link",
        info["flange_link"],
    )
    return runs, wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/vtcal_identity"))
    ap.add_argument("--save", type=Path, help="write the digests to this JSON file")
    ap.add_argument("--check", type=Path, help="compare with digests saved by --save")
    args = ap.parse_args()
    runs, wall = make_runs(args.workdir)
    now = {case: folder_digests(run) for case, run in runs.items()}
    for case, files in now.items():
        print(f"{case}: {len(files)} files, vtcal wall time {wall[case]:.2f} s")
        for name, d in files.items():
            print(f"  {d}  {name}")
    if args.save:
        args.save.write_text(json.dumps(now, indent=1, sort_keys=True) + "\n")
        print(f"saved to {args.save}")
    if args.check:
        before = json.loads(args.check.read_text())
        bad = 0
        for case in sorted(set(before) | set(now)):
            names = sorted(set(before.get(case, {})) | set(now.get(case, {})))
            for name in names:
                old, new = before.get(case, {}).get(name), now.get(case, {}).get(name)
                bad += old != new
                if old == new:
                    print(f"{case}/{name}: same")
                elif old is None or new is None:
                    print(f"{case}/{name}: DIFFERS ({'new' if old is None else 'gone'} file)")
                elif name.endswith(".parquet") and old.split("/")[0] == new.split("/")[0]:
                    print(f"{case}/{name}: DIFFERS (metadata only; table data equal)")
                else:
                    print(f"{case}/{name}: DIFFERS")
        print(f"{bad} file(s) differ" if bad else "every artefact identical")
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
