"""(T1): two error models told apart by their held-out errors on the same touch-ups, or not."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.accuracy.compare import compare_runs, told_apart_text
from pipeline.accuracy.told_apart import MIN_PAIRS, not_told_apart, paired_z, sentence


def _errors(rng: np.random.Generator, n: int, extra_mm: dict[str, float]) -> pd.DataFrame:
    """Held-out errors of several models on the same ``n`` touch-ups: a shared part (the
    touch-ups' own noise, 0.03 mm) plus each model's own (``extra_mm`` RMS)."""
    common = rng.normal(0, 0.03, (n, 3))
    rows = []
    for m, extra in extra_mm.items():
        e = np.linalg.norm(common + rng.normal(0, extra / np.sqrt(3), (n, 3)), axis=1)
        rows += [
            {"model": m, "scheme": "kfold", "touchup_id": i, "error_mm": float(v)}
            for i, v in enumerate(e)
        ]
    rows.append({"model": "a", "scheme": "loto", "touchup_id": 0, "error_mm": 9.0})
    return pd.DataFrame(rows)


def test_a_worse_model_is_told_apart_and_twins_are_not() -> None:
    rng = np.random.default_rng(7)
    t = _errors(rng, 40, {"a": 0.002, "twin": 0.002, "worse": 0.06})
    z, n = paired_z(t, "worse", "a")
    assert n == 40 and z > 3  # misses more: positive and far beyond 1.96
    res = not_told_apart(t, "a", ["a", "twin", "worse"])
    assert set(res) == {"twin", "worse"}
    assert res["twin"]["told_apart"] is False and res["worse"]["told_apart"] is True
    text = sentence("a", res)
    assert "not told apart from a" in text and "twin" in text and "worse" not in text


def test_the_pairing_keeps_the_false_alarm_rate() -> None:
    """Seeded twins (the same model error): |z| >= 1.96 in about 5 % of 400 draws."""
    rng = np.random.default_rng(8)
    hits = 0
    for _ in range(400):
        z, _ = paired_z(_errors(rng, 36, {"a": 0.01, "b": 0.01}), "a", "b")
        hits += abs(z) >= 1.96
    assert 0.02 <= hits / 400 <= 0.09, hits


def test_too_few_common_touchups_make_no_test() -> None:
    t = _errors(np.random.default_rng(9), MIN_PAIRS - 1, {"a": 0.01, "b": 0.05})
    z, n = paired_z(t, "a", "b")
    assert n == MIN_PAIRS - 1 and math.isnan(z)
    assert not_told_apart(t, "a", ["a", "b"])["b"]["told_apart"] is None
    assert sentence("a", not_told_apart(t, "a", ["a", "b"])) == ""


def test_compare_carries_the_paired_z(tmp_path: Path) -> None:
    """vtcal compare reads (T1) from identify.json's cross-validation and says it."""
    from pipeline.accuracy.evaluate import perturbed_chain, random_deviations
    from pipeline.kinematics.chain import load_chain
    from tests.test_compare import (
        URDF,  # noqa: F401  (the compare test's robot)
        make_run,
    )

    nominal = load_chain(URDF, "base_link", "flange")
    true = perturbed_chain(nominal, random_deviations(nominal, np.random.default_rng(5)))
    run = make_run(tmp_path / "r", true, 1, crossval=True)
    s = json.loads((run / "identify.json").read_text())
    s["models"] = {"full": dict(s), "mdh": dict(s)}
    s["crossval"]["paired"] = {"mdh": {"z": 0.4, "n": 48, "told_apart": False}}
    (run / "identify.json").write_text(json.dumps(s))
    runs = compare_runs([run]).runs.set_index("model")
    assert runs.loc["mdh", "heldout_z_vs_shipped"] == pytest.approx(0.4)
    assert math.isnan(runs.loc["full", "heldout_z_vs_shipped"])
    assert "not told apart" in told_apart_text(0.4) and told_apart_text(3.0) == ""
    shutil.rmtree(run)


def test_the_fleet_ranks_on_the_runs_own_kfold_and_ties_what_it_cannot_tell_apart(
    tmp_path: Path,
) -> None:
    """The audit's models x recordings matrix takes each run's k-fold figures (one home with
    the run's choice) and gives the models its paired test did not tell apart the chosen
    model's rank; the fleet line names them."""
    from pipeline.audit.audit import _tied_text
    from pipeline.audit.fleet import model_matrix, ranking
    from pipeline.audit.identity import AuditItem

    items = []
    for r, (poe, full) in enumerate([(0.0417, 0.0420), (0.0661, 0.0660)]):
        run = tmp_path / f"r{r}"
        run.mkdir()
        kfold = {"offsets": 1.2, "mdh": full, "full": full, "poe": poe}
        cv = {
            "k": 5,
            "chosen_model": "poe",
            "models": {m: {"kfold_rms_mm": e, "kfold_failed_folds": 0} for m, e in kfold.items()},
            "paired": {
                "offsets": {"z": 3.9, "n": 36, "told_apart": True},
                "mdh": {"z": 1.0, "n": 36, "told_apart": False},
                "full": {"z": 1.0, "n": 36, "told_apart": False},
            },
        }
        (run / "identify.json").write_text(json.dumps({"crossval": cv}))
        items.append(AuditItem(f"r{r}", run, "A", "m", "", "b", "f", r, pd.DataFrame()))
    mat = model_matrix(items)
    assert set(mat["note"]) == {"k-fold of the run (5 folds)"}
    r0 = mat[mat["recording"] == "r0"].set_index("model")["rank"]
    assert r0.to_dict() == {"offsets": 4, "mdh": 1, "full": 1, "poe": 1}
    rank = ranking(mat)
    assert _tied_text(rank) == "; not told apart by held-out error: " + ", ".join(rank["model"][:3])
    assert rank["model"].iloc[3] == "offsets"
