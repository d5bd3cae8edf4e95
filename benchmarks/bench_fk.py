"""Forward-kinematics throughput: vtcal's batched FK against a naive per-configuration loop.

Prints the time for 100,000 configurations of a 6-joint arm (target: under 0.2 s
on one core) and the speed-up over a plain Python loop of 4x4 products, both
measured in this run (the loop is timed on 2,000 configurations and scaled).

    python benchmarks/bench_fk.py
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from support.robots_dh import LRMATE_DH, dh_urdf  # noqa: E402

from pipeline.kinematics import fk, load_chain  # noqa: E402
from pipeline.kinematics.se3 import matrix_from_axis_angle, transform_from  # noqa: E402


def naive_fk(chain, q: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """One configuration at a time, one 4x4 product per joint."""
    out = np.empty((q.shape[0], 4, 4))
    for i, qi in enumerate(q):
        T = np.eye(4)
        k = 0
        for j in chain.joints:
            T = T @ j.T_parent_joint
            if j.actuated:
                T = T @ transform_from(matrix_from_axis_angle(j.axis, qi[k]), np.zeros(3))
                k += 1
        out[i] = T
    return out


def best_of(fn, repeats: int) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    chain = load_chain(dh_urdf(LRMATE_DH), "base_link", "flange")
    rng = np.random.default_rng(0)
    q = rng.uniform(-np.pi, np.pi, (100_000, 6))
    t_batch = best_of(lambda: fk(chain, q), 5)
    n_naive = 2_000
    t_naive = best_of(lambda: naive_fk(chain, q[:n_naive]), 2) * (q.shape[0] / n_naive)
    err = np.max(np.abs(fk(chain, q[:n_naive]) - naive_fk(chain, q[:n_naive])))
    print("forward kinematics, 6-joint arm, 100,000 configurations, one thread")
    print(
        f"  batched vtcal fk : {t_batch:8.3f} s   (target < 0.2 s: {'met' if t_batch < 0.2 else 'NOT met'})"
    )
    print(f"  naive loop       : {t_naive:8.3f} s   (timed on {n_naive}, scaled)")
    print(f"  speed-up         : {t_naive / t_batch:8.1f} x")
    print(f"  max |difference| : {err:.2e}")


if __name__ == "__main__":
    main()
