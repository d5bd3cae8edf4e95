"""Refits from a table prepared once: ``restrict`` gives what ``prepare_data`` gives on the
table with ``inlier = keep``, field by field (issue 19), and a refit what identify gives."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.evaluate import perturbed_chain, random_deviations
from pipeline.accuracy.evaluate import synthetic_touchups as synth
from pipeline.estimation.correction_frame import PAIR_COLUMNS
from pipeline.kinematics.chain import load_chain
from pipeline.measurement.data import FitData
from pipeline.stages.crossval.refit import refit, refit_config, refit_table
from pipeline.stages.crossval.stage import fold_assignment, usable_rows
from pipeline.stages.identify.data import prepare_data, prepare_table, restrict
from pipeline.stages.identify.print_shape import SHAPE_COLUMNS
from pipeline.stages.identify.stage import IdentifyConfig, IdentifyResult, identify
from pipeline.stages.identify.types import Robot

URDF = (Path(__file__).resolve().parent.parent / "pipeline/robots/lrmate.urdf").read_text()
CHAIN = load_chain(URDF, "base_link", "flange")
NAMES = CHAIN.joint_names
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]


def table(labels: list[Any], seed: int = 3) -> tuple[pd.DataFrame, list[tuple[Any, Any, float]]]:
    """Four targets labelled ``labels`` (in order of first touch), 6 touch-ups each, with
    rows already unusable, outliers with and without a reason, print-shape and pair columns.
    """
    rng = np.random.default_rng(seed)
    true = perturbed_chain(CHAIN, random_deviations(CHAIN, rng))
    tab, tg = synth(true, PIN, 4, 6, rng, noise_pin_m=3e-5, q_centre=Q_CENTRE)
    tab = tab.sample(frac=1.0, random_state=seed).reset_index(drop=True)  # targets interleaved
    code = dict(enumerate(labels))
    tab["target_id"] = pd.Series([code[int(t)] for t in tab["target_id"]], dtype=object)
    if all(isinstance(v, int) for v in labels):
        tab["target_id"] = tab["target_id"].astype(np.int64)
    M = len(tab)
    tab["weight"] = 1.0 + rng.random(M)
    tab["converged"] = True
    tab.loc[2, "converged"] = False  # not converged ...
    tab.loc[5, "weight"] = 0.0  # ... weight 0 ...
    tab.loc[7, "joint_3"] = np.nan  # ... a joint missing ...
    tab.loc[9, ["converged", "weight"]] = [False, 0.0]  # ... two reasons
    tab["inlier"] = True
    tab["reason"] = ""
    tab.loc[11, ["inlier", "reason"]] = [False, "studentized residual 5.1; leverage 0.4"]
    tab.loc[13, "inlier"] = False  # rejected without a reason
    for c in ("dx_flange", "dy_flange", "dz_flange"):
        tab[c] = rng.normal(0.0, 1e-4, M)
    for c in SHAPE_COLUMNS:
        tab[c] = rng.normal(0.0, 1.0, M)
    tab.loc[4, "view_gx"] = np.nan  # one row's print-shape lever missing: no shape unless left out
    for c in PAIR_COLUMNS:
        tab[c] = rng.random(M) * 1e-5
    d01 = float(np.linalg.norm(tg[0] - tg[1]))
    d23 = float(np.linalg.norm(tg[2] - tg[3]))
    dist = [(labels[0], labels[1], d01), (labels[2], labels[3], d23), (labels[1], "absent", 0.3)]
    return tab, dist


def assert_same(a: FitData, b: FitData) -> None:
    """Every field of two FitData equal: values, dtypes, None where None."""
    for f in dataclasses.fields(FitData):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, pd.DataFrame):
            assert isinstance(y, pd.DataFrame)
            assert list(x.columns) == list(y.columns), f.name
            assert x.dtypes.equals(y.dtypes), f.name
            assert x.equals(y), (f.name, x.compare(y))
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            assert isinstance(x, np.ndarray) and isinstance(y, np.ndarray), f.name
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert type(x) is type(y) and x == y, (f.name, x, y)


def masks(tab: pd.DataFrame) -> list[np.ndarray]:
    """The subsets cross-validation fits, and some it does not."""
    use = usable_rows(tab, NAMES)
    tid = tab["target_id"].to_numpy()
    fold = np.full(len(tab), -1)
    fold[use] = fold_assignment(tid[use], 5, np.random.default_rng(0))
    out = [use, use & (fold != 1), use & (fold != 3)]  # full fit, k-fold
    out += [use & (tid != t) for t in pd.unique(tid)]  # leave one target out
    rng = np.random.default_rng(1)
    out += [rng.random(len(tab)) < 0.6 for _ in range(3)]  # any rows, unusable ones too
    out += [np.ones(len(tab), dtype=bool), np.zeros(len(tab), dtype=bool)]
    out += [tab["target_id"].to_numpy() == tab["target_id"].iloc[0]]  # one target left
    return out


@pytest.mark.parametrize("labels", [[7, 2, 11, 4], ["B", "A", "c12", "7x"]])
def test_restrict_is_prepare_data_on_the_masked_table(labels: list[Any]) -> None:
    tab, dist = table(labels)
    cfg = IdentifyConfig(distances=dist, strict_distances=False)
    prep = prepare_table(tab, CHAIN, cfg)
    seen_drop = seen_shape = seen_none = False
    for keep in masks(tab):
        want = prepare_data(tab.assign(inlier=keep), CHAIN, cfg)
        got = restrict(prep, keep, cfg)
        assert_same(got, want)
        seen_drop |= any("no usable touch-up" in d for d in want.dropped_distances)
        seen_shape |= want.shape_g is not None
        seen_none |= want.shape_g is None and want.K > 0
    # the cases the masks were chosen for did occur
    assert seen_drop and seen_shape and seen_none
    reasons = set(prepare_data(tab, CHAIN, cfg).rows["reason"])
    assert "not converged; weight not positive" in reasons
    assert "rejected as outlier (studentized residual 5.1; leverage 0.4)" in reasons
    # a row already unusable and left out: its reasons in identify's order
    keep = np.ones(len(tab), dtype=bool)
    keep[[2, 9]] = False
    rows = restrict(prep, keep, cfg).rows
    assert rows["reason"].iloc[2] == "not converged; rejected as outlier"
    assert rows["reason"].iloc[9] == "not converged; rejected as outlier; weight not positive"
    # the result shares no array with what it came from
    got = restrict(prep, keep, cfg)
    got.d_all[:] = 1.0
    assert not np.any(prep.data.d_all == 1.0)


def test_restrict_keeps_preparation_errors_and_checks_the_mask() -> None:
    tab, dist = table([7, 2, 11, 4])
    strict = IdentifyConfig(distances=dist, strict_distances=True)
    with pytest.raises(Exception, match="absent") as exc:
        prepare_data(tab, CHAIN, strict)
    with pytest.raises(type(exc.value), match="absent"):
        prepare_table(tab, CHAIN, strict)
    prep = prepare_table(tab, CHAIN, IdentifyConfig(distances=dist, strict_distances=False))
    with pytest.raises(ValueError, match="keep has shape"):
        restrict(prep, np.ones(3, dtype=bool), IdentifyConfig())


def fitted(res: object) -> IdentifyResult:
    assert isinstance(res, IdentifyResult)
    return res


def test_a_refit_is_identify_on_the_masked_table() -> None:
    tab, dist = table(["B", "A", "c12", "7x"], seed=4)
    tab = tab.drop(columns=list(SHAPE_COLUMNS))  # no print shape: a quicker fit
    # a row with a joint missing makes the correction frame's pair-scatter average fail
    # (translation_map reads every row's joints; LinAlgError, in identify as on main)
    tab.loc[7, "joint_3"] = 0.1
    base = IdentifyConfig(model="full", distances=dist, strict_distances=False)
    full = fitted(
        identify(tab.assign(inlier=usable_rows(tab, NAMES)), URDF, "base_link", "flange", base)
    )
    cfg = refit_config(base, full.summary)
    rt = refit_table(tab, Robot.load(URDF, "base_link", "flange"), cfg)
    tid = tab["target_id"].to_numpy()
    use = usable_rows(tab, NAMES)
    for keep in (use, use & (tid != "A")):
        a = fitted(identify(tab.assign(inlier=keep), URDF, "base_link", "flange", cfg))
        b = refit(rt, keep, cfg)
        pd.testing.assert_frame_equal(a.targets, b.targets)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.p_flange_pin, b.p_flange_pin)
        assert {k: v for k, v in a.summary.items() if k != "seconds"} == {
            k: v for k, v in b.summary.items() if k != "seconds"
        }
    # a table identify refuses: every refit refuses it alike
    bad = tab.assign(touchup_id=0)
    rt_bad = refit_table(bad, Robot.load(URDF, "base_link", "flange"), cfg)
    with pytest.raises(Exception, match="more than once") as want:
        identify(bad.assign(inlier=use), URDF, "base_link", "flange", cfg)
    with pytest.raises(type(want.value), match=str(want.value)[:40]):
        refit(rt_bad, use, cfg)
