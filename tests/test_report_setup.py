"""The report says where each set-up value came from, and how the solver ended in words.

- A value ingest inferred (``camera_response`` estimated from the images, a default
  threshold, the URDF's root as base) was listed under "Set-up (recording metadata)" and
  again under "Inferred": ingest writes it into the metadata the later stages read. It is
  listed once, as inferred; a value the recording declared stays under the metadata.
- The solver row showed scipy's raw message (```ftol` termination condition is
  satisfied.``); it says "converged (cost change small)", and identify.json keeps
  scipy's message.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.report.data import RunData
from pipeline.report.html_sections import conditioning_section, run_section


def test_an_inferred_value_is_not_listed_as_recording_metadata(tmp_path: Path) -> None:
    rec = {
        "metadata": {
            "camera_response": "linear",
            "target_diameter_m": "0.010",
            "polarity": "dark_on_light",
            "base_link": "base_link",
        },
        "inferred": {
            "camera_response": "linear (estimated from the edge profiles of 12 images)",
            "base_link": "base_link (root link of the URDF)",
        },
    }
    run = run_section(RunData(tmp_path, recording=rec))
    assert dict(run["metadata"]) == {"target_diameter_m": "0.010", "polarity": "dark_on_light"}
    assert dict(run["inferred"]) == rec["inferred"]


def test_a_declared_value_stays_under_the_metadata(tmp_path: Path) -> None:
    rec = {"metadata": {"camera_response": "srgb"}, "inferred": {}}
    run = run_section(RunData(tmp_path, recording=rec))
    assert run["metadata"] == [("camera_response", "srgb")] and run["inferred"] == []


@pytest.mark.parametrize(
    "status, message, said",
    [
        (1, "`gtol` termination condition is satisfied.", "converged (gradient small)"),
        (2, "`ftol` termination condition is satisfied.", "converged (cost change small)"),
        (3, "`xtol` termination condition is satisfied.", "converged (step small)"),
        (
            4,
            "Both `ftol` and `xtol` termination conditions are satisfied.",
            "converged (cost change and step small)",
        ),  # fmt: skip
        (
            0,
            "The maximum number of function evaluations is exceeded.",
            "stopped: evaluation limit reached, not converged",
        ),  # fmt: skip
    ],
)
def test_the_solver_row_says_how_it_ended(status: int, message: str, said: str, tmp_path) -> None:
    solver = {"method": "lm", "status": status, "message": message, "nfev": 4}
    idf = {"solver": solver}
    rows = dict(conditioning_section(RunData(tmp_path, identify=idf))["summary"])
    assert rows["solver"] == f"{said} (lm, 4 evaluations)"
    assert "termination" not in rows["solver"] and "exceeded" not in rows["solver"]


def test_a_solver_without_a_status_keeps_its_message() -> None:
    from pipeline.report.html_sections import solver_status

    assert solver_status({"message": "done"}) == "done"
    assert solver_status({}) == "unknown"
