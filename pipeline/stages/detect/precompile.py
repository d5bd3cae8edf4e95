"""Compile the detector ahead of the first image, announcing a slow (first-run) compile.

The detector's fine stage is compiled by numba (:mod:`pipeline.stages.detect._jit`,
``cache=True``). On a fresh install nothing is cached yet and the first
detection waits for the compiler (~10-20 s on a 2-core machine) before any
progress can show; later runs load the cached machine code in well under a second.
:func:`compile_detector` makes that wait happen up front, on one synthetic
image of the same kind as a recording's (8-bit grey, a dark disc on a light
plate), and calls ``on_slow`` once when it has lasted ``after_s`` seconds, so the
command line can say what is happening and show it progressing instead of
sitting silent. The synthetic detection's result is discarded; the recording's
own detections are the same with or without it (same compiled code). The
camera-response estimate's compiled edge fit (:mod:`pipeline.stages.response._edge_jit`)
is warmed the same way, on a synthetic edge.

Where numba keeps the cache: ``__pycache__`` beside ``_jit.py`` when that
folder is writable, else numba's user cache folder; ``NUMBA_CACHE_DIR`` moves it.
An installed package normally has it already: building the wheel runs
:func:`compile_detector` on the built tree (``setup.py``), and numba keys the
cache on the source's content, its own version, Python's and the CPU, so a
``pip install`` on the machine that runs vtcal ships the machine code with it
(``benchmarks/bench_first_run.py``: first run within 1.5x of a warm one). A wheel
built elsewhere, another numba or a read-only install compile on the first run,
announced as before.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from pipeline.stages.detect.detector import DetectConfig, detect_target
from pipeline.stages.response.edge_fit import warm_edge_fit


def synthetic_target(size: int = 96, radius: float = 18.0) -> np.ndarray:
    """A blurred dark disc on a light plate, (size, size) uint8, off the pixel grid."""
    v, u = np.mgrid[0:size, 0:size].astype(float)
    c = 0.5 * (size - 1) + 0.3
    inside = (u - c) ** 2 + (v - c + 0.2) ** 2 < radius**2
    img = np.where(inside, 50.0, 200.0)
    return np.ascontiguousarray(
        np.clip(cv2.GaussianBlur(img, (0, 0), 1.2), 0, 255).astype(np.uint8)
    )


def compile_detector(
    config: DetectConfig | None = None,
    on_slow: Callable[[], None] | None = None,
    after_s: float = 1.0,
) -> float:
    """Run one detection on :func:`synthetic_target` so the compiled code is ready.

    Parameters
    ----------
    config : the recording's detection settings (nothing to do when ``compiled`` is off)
    on_slow : called once, from a timer thread, if this takes longer than ``after_s``
        (the compiled code was not in the cache: a first run)
    after_s : seconds before ``on_slow``

    Returns
    -------
    float : seconds it took (compiling, or loading the cache)
    """
    cfg = config or DetectConfig()
    if not cfg.compiled:
        return 0.0
    timer = threading.Timer(after_s, on_slow) if on_slow is not None else None
    t0 = time.perf_counter()
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:
        detect_target(synthetic_target(), cfg)
        warm_edge_fit()
    finally:
        if timer is not None:
            timer.cancel()
    return time.perf_counter() - t0
