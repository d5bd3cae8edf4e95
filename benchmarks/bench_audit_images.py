"""Benchmark: the audit on image-level simulated recordings (`vtcal simulate` + `vtcal run`).

    python benchmarks/bench_audit_images.py [--workdir DIR] [--per-target 6]

The touch-up-level histories of ``bench_audit.py`` draw touch-ups from the exact
model with Gaussian noise; here every recording goes through the whole chain
(rendered images, detection, the touch-up loop, ingest, touch-up extraction,
outliers), so detection bias and the loop's residual errors are in the data.
One robot (scenario ``[robot] cell_seed = 100``, ``robot_id = "img-A"``,
3 targets on a bar x ``--per-target`` poses, one capture at convergence),
recorded six times with new poses (``--seed 1..6``):

* recordings 0-2: nothing changes (two no-event comparisons);
* before 3: the camera remounted: ``[camera] mount_xyz_m`` +0.1 mm in x;
* before 4: nothing (one no-event comparison);
* before 5: the base moved: every target 1 mm further in x (``[targets] centre_m``);

plus one recording of another robot of the same model (``cell_seed = 200``),
and ``--extra`` more recordings of the first robot after the base move, nothing
changing between them (more no-event comparisons).
Prints each comparison's chi-square, dof and reading, and the counts. Each
recording takes about 25 s (simulate 13 s, run to outliers 9 s) on this machine.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MOUNT = (0.03, 0.0, 0.08)  # the scenario default
CENTRE = (0.4, 0.0, 0.12)  # the LR Mate-like cell's default
#: recording -> (cell seed, robot id, mount x shift m, centre x shift m, what happened before it)
PLAN = [
    (100, "img-A", 0.0, 0.0, "first"),
    (100, "img-A", 0.0, 0.0, "none"),
    (100, "img-A", 0.0, 0.0, "none"),
    (100, "img-A", 1e-4, 0.0, "camera"),
    (100, "img-A", 1e-4, 0.0, "none"),
    (100, "img-A", 1e-4, 1e-3, "base"),
    (200, "img-B", 0.0, 0.0, "another robot"),
]


def scenario(
    cell_seed: int, rid: str, dm: float, dc: float, per_target: int, change: str = ""
) -> str:
    m = (MOUNT[0] + dm, MOUNT[1], MOUNT[2])
    c = (CENTRE[0] + dc, CENTRE[1], CENTRE[2])
    return f"""name = "audit_images"
[robot]
name = "lrmate"
robot_id = "{rid}"
cell_seed = {cell_seed}
{change}
[camera]
mount_xyz_m = [{m[0]!r}, {m[1]!r}, {m[2]!r}]
[targets]
count = 3
bar = true
centre_m = [{c[0]!r}, {c[1]!r}, {c[2]!r}]
[touchup]
repeat_captures = 1
[poses]
per_target = {per_target}
"""


#: --histories cases: (name, [robot] lines of the event, mount shift m, the reading's test)
def _link_change() -> str:
    """joint 3's origin 0.1 mm along its nominal offset (bench_audit's link case)."""
    import numpy as np

    from pipeline.kinematics.chain import load_chain
    from pipeline.robots import builtin_urdf

    j = {j.name: j for j in load_chain(builtin_urdf("lrmate"), "base_link", "flange").actuated}
    t = np.asarray(j["joint_3"].T_parent_joint[:3, 3], dtype=float)
    d = [float(v) for v in 1e-4 * t / np.linalg.norm(t)]
    return f'change_joint = "joint_3"\nchange_dxyz_m = [{d[0]!r}, {d[1]!r}, {d[2]!r}]'


CASES = {
    "none": ("", 0.0, lambda r: r.kind == "none"),
    "joint 3 zero 0.05 deg": (
        f'change_joint = "joint_3"\nchange_dq0_rad = {0.05 * 3.141592653589793 / 180!r}',
        0.0,
        lambda r: r.kind == "arm" and r.cause == "joint_3 zero offset",
    ),
    "link 0.1 mm": (
        "LINK",
        0.0,
        lambda r: r.kind == "arm" and r.cause.startswith("link before joint_3"),
    ),
    "camera 0.1 mm": ("", 1e-4, lambda r: r.kind == "camera"),
}


def _one_recording(job: tuple[Path, str, int, str]) -> Path:
    """Simulate (or render with Mitsuba: ``renderer`` "mitsuba", its linear effects) and run
    one recording (its scenario text, seed) unless already there."""
    work, text, seed, renderer = job
    import hashlib

    tag = "" if renderer == "sim" else renderer
    key = hashlib.sha256(f"{text}{seed}{tag}".encode()).hexdigest()[:12]
    rec, run = work / f"{key}.mcap", work / "runs" / key
    if not (run / "inliers.parquet").is_file():
        toml = work / f"{key}.toml"
        toml.write_text(text)
        if renderer == "mitsuba":
            _render(toml, seed, rec)
        else:
            vtcal("simulate", "--scenario", str(toml), "--seed", str(seed), "--out", str(rec),
                  "--quiet")  # fmt: skip
        vtcal("run", str(rec), "--out", str(run), "--until", "outliers", "-q")
    return run


def _render(toml: Path, seed: int, rec: Path) -> None:
    """The scenario's recording with images Mitsuba formed (``PbrEffects.linear()``: a
    linear camera, no print or lens effects, so one robot's two recordings share their
    targets exactly), as ``benchmarks/bench_render.py`` renders its linear rows."""
    from pipeline.sim.render_pbr import PbrEffects, pbr_scenario, pbr_source
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import write_recording

    eff = PbrEffects.linear()
    write_recording(pbr_scenario(load_scenario(toml), eff), seed, rec, image_source=pbr_source(eff))


def histories(work: Path, n: int, per_target: int, workers: int, renderer: str = "sim") -> None:
    """``n`` image-level histories per case, each a new robot (cell seed) recorded twice
    (``--seed 1`` and ``2``, the case's event before the second): found, read right, and
    different robots (each history's first recording against the next history's)."""
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.audit.attribute import Reading, attribute
    from pipeline.audit.change import ALPHA, compare_estimates
    from pipeline.audit.fit import fit_item
    from pipeline.audit.identity import load_item

    link = _link_change()
    jobs, keys = [], []
    for ci, (case, (change, dm, _)) in enumerate(CASES.items()):
        change = link if change == "LINK" else change
        for h in range(n):
            cs, rid = 1000 + 100 * ci + h, f"{ci}-{h}"
            jobs.append((work, scenario(cs, rid, 0.0, 0.0, per_target), 1, renderer))
            jobs.append((work, scenario(cs, rid, dm, 0.0, per_target, change), 2, renderer))
            keys.append((case, h))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(workers) as ex:
        runs = list(ex.map(_one_recording, jobs))
    est = [fit_item(load_item(r)) for r in runs]
    print(f"bench_audit_images --histories {n} --renderer {renderer}: {len(runs)} recordings, 3 targets x "
          f"{per_target} poses, one capture each, alpha {ALPHA:g} per comparison")  # fmt: skip
    firsts = []
    for i, (case, h) in enumerate(keys):
        a, b = est[2 * i], est[2 * i + 1]
        firsts.append(a)
        d = compare_estimates(a, b)
        r = attribute(d, b) if d.changed() else Reading("none", "", "no change")
        keys[i] = (case, h, d, r)
    for case, (_, _, ok) in CASES.items():
        rows = [(d, r) for c, _, d, r in keys if c == case]
        found = sum(d.changed() for d, _ in rows)
        right = sum(bool(ok(r)) for _, r in rows)
        chis = [d.T / d.dof for d, _ in rows]
        if case == "none":
            print(f"{case:<22} false alarms {found}/{len(rows)} comparisons"
                  f" ({100 * found / len(rows):.1f} %; smallest p {min(d.p for d, _ in rows):.2g});"
                  f" chi2/dof median {np.median(chis):.2f}"
                  f" (f_dof median {np.median([d.f_dof for d, _ in rows]):.0f})")  # fmt: skip
        else:
            print(f"{case:<22} found {found}/{len(rows)} ({100 * found / len(rows):.0f} %),"
                  f" read right {right}/{len(rows)} ({100 * right / len(rows):.0f} %);"
                  f" largest p {max(d.p for d, _ in rows):.2g}")  # fmt: skip
    for case, h, d, r in keys:  # every miss, to read
        if not CASES[case][2](r):
            print(f"  miss: {case} history {h}: chi2 {d.T:.1f} on {d.dof} dof, f {d.f_dof:.0f},"
                  f" p {d.p:.2g}; {r.kind}: {r.text[:150]}")  # fmt: skip
    diff_ok = 0
    ratios: list[float] = []
    pairs = list(zip(firsts[:-1], firsts[1:], strict=True))
    for a, b in pairs:
        d = compare_estimates(a, b)
        r = attribute(d, b) if d.changed() else Reading("none", "", "")
        diff_ok += r.kind == "different_robot"
        ratios.append(d.T / max(d.dof, 1))
    same_as_diff = sum(r.kind == "different_robot" for _, _, _, r in keys)
    one = [d.T / max(d.dof, 1) for _, _, d, _ in keys]
    print(f"different robots       read as different robots {diff_ok}/{len(pairs)};"
          f" one robot read as different robots {same_as_diff}/{len(keys)};"
          f" chi2/dof of two robots: min {min(ratios):.3g}, median {np.median(ratios):.3g};"
          f" of one robot (events included): max {max(one):.3g}")  # fmt: skip
    print(f"time {time.perf_counter() - t0:.0f} s; recordings in {work}")


def vtcal(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "pipeline", *args], check=True, cwd=ROOT,
                   stdout=subprocess.DEVNULL)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=None, help="keep recordings here")
    ap.add_argument("--per-target", type=int, default=6)
    ap.add_argument("--extra", type=int, default=0, help="no-event recordings added")
    ap.add_argument(
        "--histories",
        type=int,
        default=0,
        help="instead: this many histories per case (none, joint 3 zero 0.05 deg, link 0.1 mm, "
        "camera 0.1 mm), each a new robot recorded twice",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--renderer",
        choices=["sim", "mitsuba"],
        default="sim",
        help="--histories' images: vtcal simulate's, or Mitsuba's (bench_render's linear "
        "effects; about 0.25 s a capture more)",
    )
    a = ap.parse_args()
    if a.histories:
        work = a.workdir or Path(tempfile.mkdtemp(prefix="bench_audit_images_"))
        (work / "runs").mkdir(parents=True, exist_ok=True)
        histories(work, a.histories, a.per_target, a.workers, a.renderer)
        return
    plan = PLAN + [(100, "img-A", 1e-4, 1e-3, "none")] * a.extra
    from pipeline.audit.attribute import Reading, attribute
    from pipeline.audit.change import compare_estimates
    from pipeline.audit.fit import fit_item
    from pipeline.audit.identity import load_item

    work = a.workdir or Path(tempfile.mkdtemp(prefix="bench_audit_images_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    folders = []
    for i, (cs, rid, dm, dc, _what) in enumerate(plan):
        rec, run = work / f"r{i}.mcap", work / "runs" / f"r{i}"
        if not (run / "inliers.parquet").is_file():
            toml = work / f"r{i}.toml"
            toml.write_text(scenario(cs, rid, dm, dc, a.per_target))
            vtcal("simulate", "--scenario", str(toml), "--seed", str(i + 1), "--out", str(rec),
                  "--quiet")  # fmt: skip
            vtcal("run", str(rec), "--out", str(run), "--until", "outliers", "-q")
        folders.append(run)
    est = [fit_item(load_item(f)) for f in folders]
    counts = {"none": [0, 0], "camera": [0, 0], "base": [0, 0], "another robot": [0, 0]}
    pairs = [(i - 1, i) for i in range(1, 6)] + [(0, 6), (5, 7)]
    pairs += [(i - 1, i) for i in range(8, len(plan))]
    pairs = [(ia, ib) for ia, ib in pairs if ib < len(plan)]
    for ia, ib in pairs:
        what = plan[ib][4]
        d = compare_estimates(est[ia], est[ib])
        r = attribute(d, est[ib]) if d.changed() else Reading("none", "", "no change")
        right = {"none": "none", "camera": "camera", "base": "base",
                 "another robot": "different_robot"}[what] == r.kind  # fmt: skip
        counts[what][0] += right
        counts[what][1] += 1
        print(f"r{ia} -> r{ib} ({what:13s}): chi2 {d.T:10.1f} on {d.dof} dof, p {d.p:.2g}; "
              f"{r.kind}: {r.text[:120]}")  # fmt: skip
    print(
        "read right: "
        + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in counts.items())
        + f"  ({len(plan)} recordings, 3 targets x {a.per_target} poses; "
        f"{time.perf_counter() - t0:.0f} s; recordings in {work})"
    )


if __name__ == "__main__":
    main()
