"""Rule-based rejection flags, never deletes, and states every reason."""

from __future__ import annotations

from types import SimpleNamespace

import pandas as pd

from pipeline.stages.outliers.stage import OutlierConfig, flag_outliers


def test_rules_flag_with_reasons_and_keep_rows() -> None:
    table = pd.DataFrame(
        {
            "touchup_id": [0, 1, 2, 3],
            "target_id": [0, 0, 1, 1],
            "dx_flange": 0.0,
            "dy_flange": 0.0,
            "dz_flange": 0.0,
            "weight": 1.0,
            "converged": [True, False, True, True],
            "stamp_ns": [1, 2, 3, 4],
            "j1": [0.1, 0.2, 0.3, 0.4],
            "moving": [False, False, True, False],
            "border_contact": [False, True, False, False],
        }
    )
    out = flag_outliers(table, SimpleNamespace(joint_names=["j1"]), OutlierConfig())
    assert list(out["touchup_id"]) == [0, 1, 2, 3]
    assert list(out["inlier"]) == [True, False, False, True]
    assert out.loc[1, "reason"] == "not converged; contour cut by the border"
    assert out.loc[2, "reason"] == "captured while moving"
    assert out.loc[0, "reason"] == ""
    assert list(out["j1"]) == [0.1, 0.2, 0.3, 0.4]


def test_a_final_blob_far_off_the_designated_size_is_a_lost_target() -> None:
    """An occluder taken for the target (302 px against 53 px designated) is 'target lost'."""
    table = pd.DataFrame(
        {
            "touchup_id": [0, 1, 2],
            "target_id": [0, 0, 0],
            "converged": [True, False, True],
            "stamp_ns": [1, 2, 3],
            "j1": [0.1, 0.2, 0.3],
            "lost": [False, False, False],
            "s": [53.3, 302.1, float("nan")],
            "e_s_px": [0.04, 248.8, float("nan")],
        }
    )
    out = flag_outliers(table, SimpleNamespace(joint_names=["j1"]), OutlierConfig())
    assert list(out["inlier"]) == [True, False, True]
    assert out.loc[1, "reason"] == "not converged; target lost"


def test_an_unconverged_touch_up_within_reach_of_the_correction_is_kept() -> None:
    """Stopped a few tenths of a pixel out (uneven light fooled the controller): corrected, kept.

    Beyond the correctable range, lost, or without a measured e_T it stays rejected.
    """
    table = pd.DataFrame(
        {
            "touchup_id": [0, 1, 2, 3, 4],
            "target_id": [0, 0, 0, 0, 0],
            "converged": [True, False, False, False, False],
            "stamp_ns": [1, 2, 3, 4, 5],
            "j1": [0.1, 0.2, 0.3, 0.4, 0.5],
            "lost": [False, False, False, True, False],
            "e_u": [0.1, 0.7, 3.5, 0.3, float("nan")],
            "e_v": [-0.2, -0.4, 0.1, 0.2, float("nan")],
            "e_s_px": [0.05, 0.6, 0.1, 0.1, float("nan")],
            "s": [53.3, 53.9, 53.4, 53.4, float("nan")],
        }
    )
    out = flag_outliers(table, SimpleNamespace(joint_names=["j1"]), OutlierConfig())
    assert list(out["inlier"]) == [True, True, False, False, False]
    assert out.loc[1, "reason"] == ""
    assert out.loc[1, "note"].startswith("not converged, corrected by the residual correction")
    assert bool(out.loc[1, "converged"])  # identification takes it
    assert out.loc[2, "reason"] == "not converged"
    assert out.loc[3, "reason"] == "not converged; target lost"
    assert out.loc[4, "reason"] == "not converged"
    # a spec table (no e_T columns) has nothing to correct with
    spec = table.drop(columns=["e_u", "e_v", "e_s_px"])
    assert list(
        flag_outliers(spec, SimpleNamespace(joint_names=["j1"]), OutlierConfig())["inlier"]
    ) == [True, False, False, False, False]
