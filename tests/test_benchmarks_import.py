"""Every benchmark script imports: a module moved or renamed under it shows here, not
on the day someone runs the benchmark (``bench_outliers.py`` once imported
``heldout_predictions`` from a module that never had it)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.parametrize("script", sorted(BENCH.glob("*.py")), ids=lambda p: p.name)
def test_the_benchmark_imports(script: Path) -> None:
    spec = importlib.util.spec_from_file_location(f"_bench_{script.stem}", script)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(BENCH))
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    try:
        spec.loader.exec_module(mod)  # scripts run their work under __main__ only
    finally:
        sys.path.remove(str(BENCH))
        del sys.modules[spec.name]
    assert callable(getattr(mod, "main", None)), f"{script.name}: no main()"
