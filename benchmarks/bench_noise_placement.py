"""Benchmark: where the sensor noise enters, and the long axis under an encoded response.

A face-on disc (38.3 px radius, plate 200 / target 40 grey levels of irradiance,
Gaussian blur 1 px) is imaged ``--n`` times through the simulator's sensor model
(:func:`pipeline.sim.optics.form_image`) with a linear, an sRGB and a gamma 2.2
response, each with its noise placed in one of two ways:

* **after the curve**: ``DN = 255 f(E) + N(0, 2^2)``, the simulator's ``[camera]
  noise_sigma`` with ``[optics] noise_domain = "output"`` (every row of
  ``bench_optics.py`` before the default changed; the simulator's default is now ``sensor``);
* **before the curve**: read noise of the same 2 grey levels on the irradiance,
  ``DN = 255 f(E + N(0, (2/255)^2))``, as a real sensor's read and shot noise
  enter before the camera encodes its output.

vtcal detects each image with the response declared and prints the mean long
axis and its scatter per capture, and the scatter's ratio to the linear image's
with the same placement. After the curve, an encoding's slope at the halfway
contour (``f'`` ~0.68 for sRGB at the contour's 47 % irradiance) scales the noise
seen on the irradiance by ``1 / f'``: that was the excess of the sRGB rows of
``bench_optics.py`` with noise after the curve, not the detector's. Before the curve the ratio is ~1.

    python benchmarks/bench_noise_placement.py [--n 200]
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from pipeline.sim.optics import Response, Sensor, form_image
from pipeline.stages.detect.detector import DetectConfig, detect_target

H, W, R, CX, CY = 240, 320, 38.3, 160.4, 119.7


def irradiance(ss: int = 8) -> np.ndarray:
    """The disc's irradiance (grey levels), area-sampled ``ss`` x ``ss`` and blurred 1 px."""
    yy, xx = np.mgrid[0 : H * ss, 0 : W * ss]
    inside = ((xx + 0.5) / ss - 0.5 - CX) ** 2 + ((yy + 0.5) / ss - 0.5 - CY) ** 2 < R * R
    L = np.where(inside, 40.0, 200.0).reshape(H, ss, W, ss).mean(axis=(1, 3))
    return np.asarray(cv2.GaussianBlur(L, (0, 0), 1.0))


def long_axes(kind: str, gamma: float, before: bool, n: int, seed: int = 1) -> np.ndarray:
    """Detected long axes (px) of ``n`` noisy images; response ``kind`` declared."""
    resp = Response(kind=kind, gamma=gamma) if kind == "gamma" else Response(kind=kind)
    if before:
        sen = Sensor(response=resp, noise_sigma=0.0, vignetting=0.0, read_noise_e=2.0 / 255 * 1e4)
    else:
        sen = Sensor(response=resp, noise_sigma=2.0, noise_domain="output", vignetting=0.0)
    declared = f"gamma:{gamma}" if kind == "gamma" else kind
    cfg = DetectConfig(polarity="dark_on_light", response=declared)
    L, rng, out = irradiance(), np.random.default_rng(seed), []
    for _ in range(n):
        _, grey = form_image(L, sen, principal_point=(CX, CY), rng_noise=rng, rng_optics=rng)
        r = detect_target(grey, cfg)
        if r["found"]:
            out.append(r["s"])
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=200, help="images per case")
    n = ap.parse_args().n
    print(
        f"{'response':10s} {'noise':13s} {'long axis px':>12s} {'scatter mpx':>11s} {'x linear':>8s}"
    )
    for before in (False, True):
        ref = None
        for kind, gamma in (("linear", 1.0), ("srgb", 1.0), ("gamma", 2.2)):
            s = long_axes(kind, gamma, before, n)
            sd = 1e3 * float(s.std(ddof=1))
            ref = sd if ref is None else ref
            name = "gamma 2.2" if kind == "gamma" else kind
            where = "before curve" if before else "after curve"
            print(
                f"{name:10s} {where:13s} {s.mean():12.4f} {sd:11.2f} {sd / ref:8.2f}   (n={len(s)})"
            )


if __name__ == "__main__":
    main()
