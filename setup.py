"""Packaging beyond pyproject.toml: the top-level ``schemas/``, ``reports/`` and ``spec/``
in the wheel, and the detector compiled into the wheel.

The repository keeps ``schemas/``, ``reports/`` and ``spec/`` (the file contracts:
recording, touch-up table, outputs) beside ``pipeline/``; a wheel carries them inside the
package as ``pipeline/_data/schemas``, ``pipeline/_data/reports`` and ``pipeline/_data/spec``,
where :mod:`pipeline.io.resources` looks when no checkout is beside the package.

Building the package (``pip install .``, ``pip wheel .``) also compiles the detector's
numba code once (:mod:`pipeline.stages.detect.precompile`, with the response estimate's
edge fit) into the built tree's ``__pycache__`` folders, so an installed vtcal's first run
loads machine code instead of waiting ~15-20 s for the compiler. numba keys that cache on the source's
content (sha256), its own version, the Python version and the CPU, so it serves the
machine the package was built on (a local install); elsewhere, or with another numba,
the first run compiles as before (announced). An editable install (``pip install -e .``,
the README's set-up line) imports the checkout itself, so there the code is compiled into
the checkout's own ``__pycache__`` folders (where a run would write it; an up-to-date cache
is loaded, not compiled again). ``VTCAL_NO_PRECOMPILE=1`` skips the step. A failed compile
only leaves the cache out.
"""

import os
import subprocess
import sys

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

#: the numba modules (folder under pipeline/stages, cache file prefix) compiled into the build
JIT_MODULES = (("detect", "_jit."), ("response", "_edge_jit."))

DATA = {
    "pipeline._data.schemas": "schemas",
    "pipeline._data.reports": "reports",
    "pipeline._data.spec": "spec",
}

#: run in a child interpreter on the built tree (its stages/detect/_jit.py is the one installed)
_COMPILE = """
import sys
sys.path.insert(0, sys.argv[1])
import pipeline
assert pipeline.__file__.startswith(sys.argv[1]), pipeline.__file__
from pipeline.stages.detect.precompile import compile_detector
print(f"{compile_detector():.1f}")
"""


class BuildWithDetector(build_py):
    """``build_py``, then the detector compiled into the built tree (module docstring)."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            # the editable install imports the checkout: compile into it, keep its cache
            self._compile(os.path.dirname(os.path.abspath(__file__)))
            return
        build_lib = os.path.abspath(self.build_lib)
        # an earlier build's cache (pip builds in the tree's build/): made again or left out
        for folder, prefix in JIT_MODULES:
            cache = os.path.join(build_lib, "pipeline", "stages", folder, "__pycache__")
            for name in os.listdir(cache) if os.path.isdir(cache) else ():
                if name.startswith(prefix) and name.endswith((".nbi", ".nbc")):
                    os.remove(os.path.join(cache, name))
        self._compile(build_lib)

    @staticmethod
    def _compile(build_lib: str) -> None:
        """Compile the detector of the tree ``build_lib`` in a child interpreter."""
        if os.environ.get("VTCAL_NO_PRECOMPILE"):
            return
        env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
        env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
        try:
            proc = subprocess.run(
                [sys.executable, "-c", _COMPILE, build_lib],
                env=env,
                capture_output=True,
                text=True,
                timeout=900,
            )
        except (OSError, subprocess.TimeoutExpired) as exc:
            print(f"vtcal: detector not precompiled ({exc}); the first run compiles it")
            return
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["?"])[-1]
            print(f"vtcal: detector not precompiled ({tail}); the first run compiles it")
        else:
            print(f"vtcal: detector compiled into the package ({proc.stdout.strip()} s)")


setup(
    packages=find_packages(include=["pipeline", "pipeline.*"]) + list(DATA),
    package_dir={"": ".", **DATA},
    package_data={
        "pipeline": ["robots/*.urdf", "py.typed"],
        "pipeline._data.schemas": ["*.json", "ros2/*/msg/*.msg"],
        "pipeline._data.reports": ["*.j2", "*.css"],
        "pipeline._data.spec": ["*.md"],
    },
    cmdclass={"build_py": BuildWithDetector},
)
