"""Benchmark: the fleet audit on simulated histories with events at known places.

    python benchmarks/bench_audit.py [--histories 20] [--recordings 6] [--per-target 12]

Histories of LR Mate-like robots (:mod:`pipeline.sim.history`: touch-up level,
3 targets x ``--per-target`` touch-ups, a calibration bar, 0.01 mm contact noise,
new poses each recording). Each history has ``--recordings`` recordings of one
robot; every robot is a new seed (deviations, camera mount, cell). Cases:

* **no event**: the false-alarm rate of the change test, per comparison and per
  history (any alarm in it), at ``alpha = 0.01``;
* one event before recording 3: **joint offset** (joint 3's zero +0.05 deg),
  **link** (joint 3's origin +0.1 mm along the upper arm), **camera** remount
  (pin moved 0.1 mm), **base** moved (1 mm, 1 mrad), and beyond those
  joint 5's zero +0.05 deg and a **thermal** growth of every link by 100 ppm
  (seen through the calibration bar): detection (the event's
  comparison flagged), the reading right (arm: that joint's zero / that link;
  camera; base), and the other comparisons of those histories (false alarms);
* the drift figure of the event's recording ((D3) of :mod:`pipeline.audit.drift`:
  the pin motion of the change read, at the new recording's poses) against the
  true change ((D1) between the true robots before and after, the same poses);
* **different robots**: the first recording of robot ``i`` against robot ``i+1``'s.

Every figure is printed with its counts. Three robots x six recordings is one
history per robot here; the goal: >= 95 % found, <= 5 % false alarms.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.audit.attribute import Reading, attribute  # noqa: E402
from pipeline.audit.change import ALPHA, compare_estimates  # noqa: E402
from pipeline.audit.drift import drift_m, read_drift_m  # noqa: E402
from pipeline.audit.fit import fit_item  # noqa: E402
from pipeline.audit.identity import AuditItem  # noqa: E402
from pipeline.io.known_distances import parse_distances  # noqa: E402
from pipeline.robots import builtin_urdf  # noqa: E402
from pipeline.sim.history import Event, HistoryRecording, make_history  # noqa: E402

AT = 3
CASES = {
    "none": (None, lambda r: r.kind == "none"),
    "joint offset 0.05 deg": (
        Event("joint_offset", np.radians(0.05), "joint_3"),
        lambda r: r.kind == "arm" and r.cause == "joint_3 zero offset",
    ),
    "link 0.1 mm": (
        Event("link_length", 1e-4, "joint_3"),
        lambda r: r.kind == "arm" and r.cause.startswith("link before joint_3"),
    ),
    "camera remount 0.1 mm": (Event("camera", 1e-4), lambda r: r.kind == "camera"),
    "joint 5 offset 0.05 deg": (
        Event("joint_offset", np.radians(0.05), "joint_5"),
        lambda r: r.kind == "arm" and r.cause == "joint_5 zero offset",
    ),
    "thermal 100 ppm": (
        Event("thermal", 1e-4),
        lambda r: r.kind == "arm" and r.cause.startswith("thermal growth"),
    ),
    "base moved 1 mm": (Event("base", 1e-3), lambda r: r.kind == "base"),
}


def item(r: HistoryRecording) -> AuditItem:
    return AuditItem(
        r.name, Path(r.name), r.robot_id, r.robot, builtin_urdf(r.robot), "base_link", "flange",
        r.stamp_ns, r.table, parse_distances(r.known_distances),
    )  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--histories", type=int, default=20, help="histories per case")
    ap.add_argument("--recordings", type=int, default=6)
    ap.add_argument("--per-target", type=int, default=12)
    ap.add_argument("--alpha", type=float, default=ALPHA, help="the change test's level")
    ap.add_argument("--first-seed", type=int, default=0, help="histories use seeds after it")
    ap.add_argument(
        "--cases", nargs="+", default=list(CASES), metavar="CASE",
        help="cases to run (default: all): " + "; ".join(CASES),
    )  # fmt: skip
    a = ap.parse_args()
    alpha = a.alpha
    t0 = time.perf_counter()
    print(
        f"bench_audit: {a.histories} histories per case x {a.recordings} recordings, 3 targets x "
        f"{a.per_target} touch-ups, alpha {alpha} per comparison"
    )
    firsts = []
    seed = a.first_seed
    all_fa = all_other = 0
    null_p: list[float] = []  # p-values of every comparison without an event
    for case in a.cases:
        event, right = CASES[case]
        found = named = 0
        fa = n_other = hist_fa = 0
        ratios = []
        for _h in range(a.histories):
            seed += 1
            hist = make_history(
                f"R{seed}", {AT: event} if event else {}, seed=seed,
                n_recordings=a.recordings, per_target=a.per_target,
            )  # fmt: skip
            est = [fit_item(item(r)) for r in hist]
            firsts.append(est[0])
            any_fa = False
            for i in range(1, len(hist)):
                d = compare_estimates(est[i - 1], est[i])
                if event is not None and i == AT:
                    found += d.changed(alpha)
                    seen = d.changed(alpha)
                    reading = attribute(d, est[i], alpha) if seen else Reading("none", "", "")
                    named += seen and right(reading)
                    truth = drift_m(
                        (hist[i - 1].true_chain, hist[i - 1].truth.p_flange_pin),
                        (hist[i].true_chain, hist[i].truth.p_flange_pin), est[i].q,
                    )  # fmt: skip
                    got = read_drift_m(est[i], d, reading)
                    if not np.isfinite(got):  # no single cause read: (D1), as vtcal audit does
                        got = drift_m(
                            (est[i - 1].result.chain, est[i - 1].result.p_flange_pin),
                            (est[i].result.chain, est[i].result.p_flange_pin), est[i].q,
                        )  # fmt: skip
                    if truth > 1e-6:  # a moved base leaves the robot as it was
                        ratios.append(got / truth)
                else:
                    n_other += 1
                    fa += d.changed(alpha)
                    any_fa |= d.changed(alpha)
                    null_p.append(float(d.p))
            hist_fa += any_fa
        all_fa, all_other = all_fa + fa, all_other + n_other
        line = f"{case:24s}"
        if event is not None:
            line += (
                f" found {found}/{a.histories} ({100 * found / a.histories:.0f} %), named right "
                f"{named}/{a.histories} ({100 * named / a.histories:.0f} %);"
            )
        line += (
            f" false alarms {fa}/{n_other} comparisons ({100 * fa / max(n_other, 1):.1f} %),"
            f" {hist_fa}/{a.histories} histories with one ({100 * hist_fa / a.histories:.0f} %)"
        )
        print(line)
        for what, rs in (("true change", ratios),):
            if not rs:
                continue
            r = np.array(rs)
            within = int(np.sum(np.abs(r - 1) <= 0.2))
            print(
                f"{'':24s} drift / {what}: median {np.median(r):.3f}, range "
                f"{r.min():.3f}-{r.max():.3f}, within 20 %: {within}/{len(r)}"
            )
    print(
        f"{'every case':24s} false alarms {all_fa}/{all_other} comparisons without an event "
        f"({100 * all_fa / max(all_other, 1):.2f} %, alpha {100 * alpha:g} %)"
    )
    pv = np.array(null_p)
    if pv.size:
        levels = ", ".join(
            f"{100 * lv:g} %: {int(np.sum(pv < lv))} ({100 * np.mean(pv < lv):.2f} %)"
            for lv in (0.01, 0.005, 0.001)
        )
        print(f"{'':24s} the same comparisons at other levels: {levels}")
    diff_ok = 0
    pairs = list(zip(firsts, firsts[1:], strict=False))
    for ea, eb in pairs:
        d = compare_estimates(ea, eb)
        diff_ok += d.changed(alpha) and attribute(d, eb, alpha).kind == "different_robot"
    print(f"{'different robots':24s} read as different robots {diff_ok}/{len(pairs)}")
    print(f"time {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
