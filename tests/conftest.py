"""Shared test fixtures: paths to the shared spec sample and the repo."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
SAMPLE = SHARED / "samples" / "conformance_lrmate_small.mcap"

sys.path.insert(0, str(Path(__file__).resolve().parent))


@pytest.fixture(scope="session")
def conformance_sample() -> Path:
    if not SAMPLE.exists():
        if os.environ.get("CI"):
            pytest.fail(f"conformance sample not found at {SAMPLE}")
        pytest.skip(f"conformance sample not found at {SAMPLE}")
    return SAMPLE


@pytest.fixture(scope="session")
def conformance_truth(conformance_sample: Path) -> dict:
    import json

    return json.loads(Path(str(conformance_sample) + ".truth.json").read_text())
