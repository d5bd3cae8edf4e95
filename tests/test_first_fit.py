"""The correction frame's first fit is made once per process for the same rows and settings.

``vtcal run``'s outliers stage identifies the inliers (model ``full``, 4 predicted-error
poses, no guardrails) and the identify stage identifies them again (every model, 200
poses, guardrails): the first fit of the correction frame is the same fit, made once.
"""

from __future__ import annotations

import collections
import json
from pathlib import Path

import pandas as pd
import pytest

import pipeline.stages.identify.stage as stage
from pipeline.stages.identify import first_fit
from pipeline.stages.identify.stage import IdentifyConfig, identify


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> collections.Counter[tuple[str, bool]]:
    """Fits made, by (model, first fit), with no first fit kept from earlier tests."""
    calls: collections.Counter[tuple[str, bool]] = collections.Counter()
    real = stage._identify_one

    def spy(name, robot, data, cfg):  # type: ignore[no-untyped-def]
        calls[(name, cfg.prediction_only and cfg.correction_frame == "nominal")] += 1
        return real(name, robot, data, cfg)

    monkeypatch.setattr(stage, "_identify_one", spy)
    first_fit.forget()
    yield calls
    first_fit.forget()


TRUTH = Path(__file__).resolve().parents[1] / "datasets/samples/sample_lrmate.mcap.truth.json"


def _table(lrmate_run: Path) -> tuple[pd.DataFrame, str, str, str, list[tuple[int, int, float]]]:
    """The sample's converged touch-ups (conftest's ``lrmate_run``), its robot and distance."""
    truth = json.loads(TRUTH.read_text())
    table = pd.read_csv(lrmate_run.parent / "table.csv")
    a, b = truth["known_distances"][0]["labels"]
    dist = [(int(a), int(b), float(truth["known_distances"][0]["metres"]))]
    return table, truth["nominal_urdf"], truth["base_link"], truth["flange_link"], dist


def test_the_outliers_and_identify_fits_share_their_first_fit(
    lrmate_run: Path, counted: collections.Counter[tuple[str, bool]]
) -> None:
    table, urdf, base, flange, dist = _table(lrmate_run)
    as_outliers = IdentifyConfig(
        model="full", distances=dist, n_workspace=4, check_plausibility=False
    )
    as_identify = IdentifyConfig(model="offsets", distances=dist, target_diameter_m=0.01)
    identify(table, urdf, base, flange, as_outliers)
    again = identify(table, urdf, base, flange, as_identify)
    assert counted[("full", True)] == 1  # the old code fitted it twice
    assert counted[("offsets", False)] == 1
    # the same result as with the first fit made afresh
    first_fit.forget()
    fresh = identify(table, urdf, base, flange, as_identify)
    assert counted[("full", True)] == 2
    assert again.summary["correction_frame"] == fresh.summary["correction_frame"]
    pd.testing.assert_frame_equal(again.parameters, fresh.parameters)


def test_other_rows_or_settings_make_their_own_first_fit(
    lrmate_run: Path, counted: collections.Counter[tuple[str, bool]]
) -> None:
    table, urdf, base, flange, dist = _table(lrmate_run)
    cfg = IdentifyConfig(model="offsets", distances=dist)
    identify(table, urdf, base, flange, cfg)
    identify(table.iloc[1:], urdf, base, flange, cfg)  # one touch-up fewer
    identify(
        table, urdf, base, flange, IdentifyConfig(model="offsets", distances=dist, data_tol=1e-5)
    )
    assert counted[("full", True)] == 3
