"""The report's 'measured' line, from a recording's ``measurement`` metadata record."""

from __future__ import annotations

from pipeline.live.summary import as_metadata, summarize
from pipeline.report.html_sections import measurement_text


def _touchup(converged: bool, reason: str = "converged") -> dict[str, object]:
    return {"converged": converged, "reason": reason, "cell_s": 6.0, "wall_s": 0.3, "captures": 5}


def test_measurement_line_round_trips_through_the_metadata_record(tmp_path: object) -> None:
    tus = [_touchup(True)] * 4 + [_touchup(False, "lost_target")]
    kv = as_metadata(summarize(tus, 6, 2, tmp_path))  # type: ignore[arg-type]
    assert "wall_s" not in kv and "recording" not in kv
    text = measurement_text(kv)
    assert text == (
        "by vtcal measure: 4 of 6 planned touch-ups converged (gave up: lost_target 1); "
        "25 captures; measuring took 0.5 min of cell time; over 2 sessions (resumed)"
    )


def test_a_recording_that_does_not_say_gets_no_line() -> None:
    assert measurement_text({}) == ""
