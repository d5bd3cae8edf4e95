"""Cross-validation: held-out error per model, choice by held-out error, agreement with truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.accuracy.evaluate import (
    perturbed_chain,
    pin_positions,
    random_deviations,
    register_points,
)
from pipeline.accuracy.evaluate import synthetic_touchups as synth
from pipeline.io.artefacts import read_artefact, write_artefact
from pipeline.kinematics.chain import load_chain
from pipeline.stages.crossval.predict import heldout_predictions
from pipeline.stages.crossval.stage import (
    CrossvalConfig,
    cross_validate,
    fold_assignment,
    usable_rows,
)
from pipeline.stages.identify.stage import IdentifyConfig

URDF = (Path(__file__).resolve().parent.parent / "pipeline/robots/lrmate.urdf").read_text()
PIN = np.array([0.01, -0.02, 0.2])
Q_CENTRE = [0.0, 0.3, -0.3, 0.0, -0.8, 0.0]


def cell(seed: int, per_target: int = 10, noise: float = 3e-5):  # type: ignore[no-untyped-def]
    chain = load_chain(URDF, "base_link", "flange")
    rng = np.random.default_rng(seed)
    true = perturbed_chain(chain, random_deviations(chain, rng))
    tab, tg = synth(true, PIN, 3, per_target, rng, noise_pin_m=noise, q_centre=Q_CENTRE)
    dist = [(0, 2, float(np.linalg.norm(tg[0] - tg[2])))]
    return tab, tg, true, dist


def test_held_out_error_picks_the_model_training_error_would_not_trust(tmp_path: Path) -> None:
    tab, _, _, dist = cell(21)
    # two rejected rows stay out of every fit and every score
    tab["inlier"] = True
    tab.loc[[3, 14], "inlier"] = False
    res = cross_validate(
        tab,
        URDF,
        "base_link",
        "flange",
        IdentifyConfig(model="all", distances=dist),
        CrossvalConfig(models=["full", "offsets"], k=5),
    )
    s = res.summary["models"]
    assert res.chosen_model == "full"
    assert s["full"]["kfold_rms_mm"] < 0.5 * s["offsets"]["kfold_rms_mm"]
    # held-out error is larger than the training error of the same model
    for m in ("full", "offsets"):
        assert s[m]["kfold_rms_mm"] > s[m]["train_rms_mm"]
        assert s[m]["kfold_n"] == 28 and s[m]["loto_n"] == 28
    assert "held-out" in res.summary["choice"] and "not training" in res.summary["choice"]
    assert not set(res.table["touchup_id"]) & {3, 14}
    assert set(res.table["scheme"]) == {"kfold", "loto"}
    # the table is a valid artefact
    write_artefact(tmp_path / "crossval.parquet", res.table, "crossval", stage="crossval")
    back = read_artefact(tmp_path / "crossval.parquet", "crossval")
    assert len(back) == len(res.table)


def test_kfold_error_agrees_with_the_truth_within_30_percent() -> None:
    """Held-out RMS against the error of the same fold models measured against the truth.

    Truth: each fold's model is registered to the true robot (one rigid motion over
    every touch-up pose) and its predicted pin at the held-out touch-ups is compared
    with the true target the pin was driven to (the touch-up's own noise included,
    as it is in any held-out residual). The robot deviates in its joint offsets only
    and the model is ``offsets``: every error the model makes is one the touch-ups
    see. (Errors the fitted target positions absorb -- a nearly constant offset over
    one target's poses -- are invisible to any touch-up residual, held out or not;
    docs/outliers.md gives the figures.)
    """
    chain = load_chain(URDF, "base_link", "flange")
    names = chain.joint_names
    for seed in (31, 32, 33, 34):
        rng = np.random.default_rng(seed)
        dev = {j: {"dq0_rad": 3 * v["dq0_rad"]} for j, v in random_deviations(chain, rng).items()}
        true = perturbed_chain(chain, dev)
        tab, tg = synth(true, PIN, 3, 12, rng, noise_pin_m=3e-5, q_centre=Q_CENTRE)
        dist = [(0, 2, float(np.linalg.norm(tg[0] - tg[2])))]
        cfg = IdentifyConfig(model="offsets", distances=dist)
        res = cross_validate(tab, URDF, "base_link", "flange", cfg, CrossvalConfig(k=5, loto=False))
        use = usable_rows(tab, names)
        fold = np.full(len(tab), -1)
        fold[use] = fold_assignment(tab["target_id"].to_numpy()[use], 5, np.random.default_rng(0))
        pr = heldout_predictions(tab, use, fold, URDF, "base_link", "flange", cfg, every_row=True)
        errs: list[float] = []
        for _, g in pr.groupby("fold"):
            rows = g["row"].to_numpy()
            pm = g[["px", "py", "pz"]].to_numpy()
            p_true = pin_positions(true, PIN, tab[names].to_numpy()[rows])
            R, t, _ = register_points(pm, p_true, scale=False)
            held = g["held"].to_numpy()
            target_true = tg[tab["target_id"].to_numpy()[rows]]
            errs += list(np.linalg.norm(pm @ R.T + t - target_true, axis=1)[held])
        truth_rms = float(np.sqrt(np.mean(np.square(errs)))) * 1e3
        ratio = res.summary["models"]["offsets"]["kfold_rms_mm"] / truth_rms
        assert abs(ratio - 1) < 0.3, (seed, ratio)


def test_unfittable_folds_are_recorded_not_fatal() -> None:
    tab, _, _, dist = cell(41, per_target=3)  # 9 touch-ups: too few for the full model
    res = cross_validate(
        tab,
        URDF,
        "base_link",
        "flange",
        IdentifyConfig(model="all", distances=dist),
        CrossvalConfig(models=["full", "offsets"], k=3),
    )
    full = res.table[res.table["model"] == "full"]
    assert len(full) and full["error_mm"].isna().all()
    assert full["status"].str.contains("not fitted").all()
    assert res.chosen_model == "offsets"
    assert res.summary["models"]["full"]["kfold_rms_mm"] is None  # strict JSON, no NaN


def test_fold_assignment_keeps_training_data_for_every_target() -> None:
    t = np.array([0] * 7 + [1] * 3 + [2] * 12)
    f = fold_assignment(t, 5, np.random.default_rng(0))
    for k in range(5):
        for target in (0, 1, 2):
            assert np.sum((t == target) & (f != k)) >= 2
    assert (
        pd.Series(f[t == 2]).value_counts().max() - pd.Series(f[t == 2]).value_counts().min() <= 1
    )


def test_the_choice_names_a_different_training_choice_only_when_there_is_one() -> None:
    """Issue 35: 'the smallest training RMS (poe, 0.0198 mm) would have chosen differently'
    while the chosen full showed 0.0198 too and elastic (0.0190, fitted but not
    cross-validated) was the smallest."""
    from pipeline.stages.crossval.stage import _choose

    def m(kfold: float, train: float) -> dict:
        return {"kfold_rms_mm": kfold, "train_rms_mm": train, "kfold_failed_folds": 0,
                "urdf_exact": True, "n_identified": 18}  # fmt: skip

    models = {"full": m(0.0586, 0.019812), "poe": m(0.0590, 0.019801), "offsets": m(0.7, 0.52)}
    chosen, text = _choose(models)
    assert chosen == "full"
    assert "poe" not in text and "would have chosen the same" in text  # a fifth-digit tie
    trained = {k: v["train_rms_mm"] for k, v in models.items()} | {"elastic": 0.0190}
    chosen, text = _choose(models, trained)
    assert "the smallest training RMS (elastic, 0.0190 mm, not cross-validated)" in text
    assert "would have chosen differently" in text
