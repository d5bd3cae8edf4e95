"""Benchmark: the camera-response estimate's edge fits, compiled against the NumPy reference.

The estimate (``pipeline.stages.image.response_estimate``) fits the edge model
(R1)-(R2) to 12 edge profiles under some 19 trial curves (a grid of 10 power
laws, a bounded search, linear, sRGB): ~230 Levenberg-Marquardt fits of a few
thousand pixels each, on ingest's critical path (detection waits for the
curve). For each recording this script collects the edge profiles the estimate
sees in ``vtcal run`` (an in-process ingest, the estimate's input recorded),
then times ``estimate_from_profiles`` on copies of them two ways, in one run:

- ``reference``: each fit as before it was compiled, ``least_squares(method="lm")``
  on the NumPy residual and Jacobian (:class:`EdgeFit`, one QR per call);
- ``compiled``: :func:`pipeline.stages.response.edge_fit.fit_edge` as it is
  (one compiled pass per residual and Jacobian, ``leastsq``);

CPU seconds, the best of ``--repeat`` (single-threaded numerics). It prints
the ratio, and checks the two estimates agree: the same curve, votes and
note, and the largest relative difference of the float figures.

    python benchmarks/bench_response_fit.py [--workdir DIR] [--repeat 5]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "datasets" / "samples" / "sample_lrmate.mcap"


def recordings(workdir: Path) -> dict[str, Path]:
    """The shipped sample and ``bench_run_stages``' standard cells (simulated there once)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_run_stages

    return {"sample": SAMPLE, **bench_run_stages.simulate(workdir)}


def profiles_of(rec: Path) -> list[Any]:
    """The edge profiles ``estimate_from_profiles`` is given in an ingest of ``rec``."""
    import pipeline.stages.image.response_estimate as rest
    from pipeline.run.orchestrator import RunConfig, ingest_configs
    from pipeline.stages.ingest.stage import ingest_recording

    seen: list[list[Any]] = []
    real = rest.estimate_from_profiles

    def spy(profiles: Any, *a: Any, **k: Any) -> Any:
        seen.append([copy.deepcopy(p) for p in profiles if p is not None])
        return real(profiles, *a, **k)

    rest.estimate_from_profiles = spy
    try:
        cfg = ingest_configs(RunConfig())
        ingest_recording(rec, cfg["ingest"], cfg["detect"])
    finally:
        rest.estimate_from_profiles = real
    if not seen:
        raise SystemExit(f"{rec}: no response estimate made (a declared curve?)")
    return seen[-1]


def reference_fit(d, du, dv, E, w, x0, xtol=1e-10):  # type: ignore[no-untyped-def]
    """The fit before it was compiled: ``least_squares`` on the NumPy :class:`EdgeFit`."""
    from scipy.optimize import least_squares

    from pipeline.stages.response.edge_fit import EdgeFit

    fit = EdgeFit(d, du, dv, E * w, w)
    sol = least_squares(fit.residual, x0, jac=fit.jacobian, method="lm", xtol=xtol)
    return float(np.sum(sol.fun**2)), np.asarray(sol.x, dtype=float)


def timed(profiles: list[Any], repeat: int, reference: bool) -> tuple[float, Any]:
    """Best CPU seconds of ``estimate_from_profiles`` on fresh copies, and its estimate."""
    import pipeline.stages.image.response_estimate as rest

    real = rest.fit_edge
    if reference:
        rest.fit_edge = reference_fit
    try:
        best, est = math.inf, None
        for _ in range(repeat):
            ps = copy.deepcopy(profiles)
            for p in ps:
                p.fits.clear()
            t0 = time.process_time()
            est = rest.estimate_from_profiles(ps)
            best = min(best, time.process_time() - t0)
    finally:
        rest.fit_edge = real
    return best, est


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_response_fit"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    from pipeline.stages.response.edge_fit import warm_edge_fit

    warm_edge_fit()  # the compiled kernel loaded (or compiled) before any timing
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}; CPU ms, best of {args.repeat}")
    print(
        f"{'recording':<11}{'profiles':>9}{'reference':>11}{'compiled':>10}{'ratio':>7}"
        f"{'curve':>8}{'same':>6}{'max rel diff':>14}"
    )
    for label, rec in recordings(args.workdir).items():
        profiles = profiles_of(rec)
        t_ref, ref = timed(profiles, args.repeat, reference=True)
        t_new, new = timed(profiles, args.repeat, reference=False)
        a, b = ref.to_dict(), new.to_dict()
        same = all(a[k] == b[k] for k in a if not isinstance(a[k], float))
        diff = max(
            abs(a[k] - b[k]) / max(abs(a[k]), 1e-300)
            for k in a
            if isinstance(a[k], float) and math.isfinite(a[k])
        )
        print(
            f"{label:<11}{len(profiles):>9}{1e3 * t_ref:>11.0f}{1e3 * t_new:>10.0f}"
            f"{t_ref / t_new:>7.2f}{new.response.spec:>8}{'yes' if same else 'NO':>6}{diff:>14.1e}"
        )
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
