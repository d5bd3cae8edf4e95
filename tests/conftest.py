"""Shared test fixtures: paths to the shared spec sample and the repo."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import pytest

from pipeline.run.threads import prefer_one_thread

prefer_one_thread()  # as the CLI does, before numpy loads: in-process runs match vtcal's own

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


@pytest.fixture(scope="session")
def lrmate_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small run folder: `vtcal identify` on the sample's converged touch-ups (about a second).

    Beside it: ``table.csv`` (integer target ids, no stamps) and ``nominal.urdf``;
    the sample's known distance is given, so the scale is identified.
    """
    import json

    import pandas as pd

    from pipeline.cli import main

    truth_path = REPO / "datasets" / "samples" / "sample_lrmate.mcap.truth.json"
    truth = json.loads(truth_path.read_text())
    tmp = tmp_path_factory.mktemp("lrmate")
    rows = [
        {
            "touchup_id": i,
            "target_id": tu["label"],
            **dict(zip(truth["joint_names"], tu["q"], strict=True)),
        }
        for i, tu in enumerate(truth["touchups"])
        if tu["converged"]
    ]
    pd.DataFrame(rows).to_csv(tmp / "table.csv", index=False)
    (tmp / "nominal.urdf").write_text(truth["nominal_urdf"])
    kd = truth["known_distances"][0]
    a, b = kd["labels"]
    out = tmp / "run"
    try:
        main(["identify", str(tmp / "table.csv"), "--urdf", str(tmp / "nominal.urdf"),
              "--out", str(out), "--distance", f"{a}:{b}={kd['metres']}", "--no-report"])  # fmt: skip
    except SystemExit as exc:
        assert not exc.code, exc.code
    return out


def _docs_summary() -> str | None:
    mod = sys.modules.get("test_docs_commands")
    if mod is not None and getattr(mod, "TALLY", None):
        return str(mod.summary_line())
    return None


_FROM_WORKERS: list[str] = []


def pytest_sessionfinish(session: pytest.Session) -> None:
    """A pytest-xdist worker hands the docs runner's counts to the controller."""
    out = getattr(session.config, "workeroutput", None)
    line = _docs_summary()
    if out is not None and line:
        out["docs_summary"] = line


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: Any) -> None:
    """The controller keeps what each worker counted (pytest-xdist's hook)."""
    line = getattr(node, "workeroutput", {}).get("docs_summary")
    if line:
        _FROM_WORKERS.append(line)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The docs-as-tests runner's counts, in CI's log (tests/test_docs_commands.py)."""
    for line in [_docs_summary(), *_FROM_WORKERS]:
        if line:
            terminalreporter.write_line(line)
