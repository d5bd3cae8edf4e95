"""One thread per numeric library unless the user says otherwise.

vtcal's linear algebra is thousands of small problems (a few hundred rows at
most): a multi-threaded BLAS gains nothing on them, and on a busy machine its
threads wait for each other. Measured on this project's shared 2-core machine
(load 4-6): ``vtcal run --no-report`` of the standard LR Mate-like cell took
6.2-6.4 s with one BLAS thread and 21-27 s with OpenBLAS's default two, with
byte-identical artefacts; the shipped sample's ingest 3.3 s against 27.9 s
(camera-response estimation: ~4,000 small ``lstsq`` calls).

The limits are environment variables the libraries read when they load, so
:func:`prefer_one_thread` must run before numpy is imported; the CLI calls it
first thing. A variable the user set is left as it is (``OPENBLAS_NUM_THREADS=2
vtcal run ...`` still gets two threads).
"""

from __future__ import annotations

import os

#: the variables numeric libraries read for their thread count
ONE_THREAD: dict[str, str] = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


def prefer_one_thread() -> None:
    """Default every library in :data:`ONE_THREAD` to one thread (user settings win)."""
    for key, value in ONE_THREAD.items():
        os.environ.setdefault(key, value)
