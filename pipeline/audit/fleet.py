"""Which error model predicts best across the fleet: a models x recordings matrix.

Per recording and error model, the held-out error the run itself shipped on: its
k-fold cross-validation (``identify.json["crossval"]``, one home with the run's
choice of model). Where the run did not cross-validate a model, the two-fold
held-out consistency (:func:`pipeline.audit.fit.heldout_mm`: fitted on every
other touch-up of each target, judged on the rest, and the other way round),
said in the row's ``note``. Per recording the models are ranked (1 = lowest
held-out error); a model the run's paired test (T1 of
:mod:`pipeline.accuracy.told_apart`) does not tell apart from the run's
chosen model shares its rank. Overall, by the median of their ranks, then by the
RMS of their held-out errors over the recordings where every model could be fitted.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.audit.fit import heldout_mm
from pipeline.audit.identity import AuditItem

#: the error models compared by default
MODELS = ("offsets", "mdh", "full", "poe")

#: a run's own k-fold figures: ``({model: (kfold_rms_mm, note)}, chosen, [tied models])``
Crossval = tuple[dict[str, tuple[float, str]], str, list[str]]


def model_matrix(
    items: list[AuditItem], models: tuple[str, ...] = MODELS, workers: int = 1
) -> pd.DataFrame:
    """One row per (recording, model): ``robot_id, recording, model, heldout_mm, rank, note``.

    ``workers``: processes for the fits (:func:`pipeline.stages.parallel_map.parallel_map`;
    0 = the free cores), one task per (recording, model); the results are the serial map's.
    """
    from pipeline.stages.parallel_map import parallel_map

    runs = [run_crossval(it) for it in items]
    tasks = heldout_tasks(runs, models)
    res = parallel_map(lambda t: heldout_mm(items[t[0]], t[1]), tasks, workers)
    return matrix_table(items, models, runs, dict(zip(tasks, res, strict=True)))


def heldout_tasks(runs: list[Crossval], models: tuple[str, ...]) -> list[tuple[int, str]]:
    """``(recording index, model)`` whose held-out figure the runs' own k-fold lacks."""
    return [(i, m) for i in range(len(runs)) for m in models if m not in runs[i][0]]


def matrix_table(
    items: list[AuditItem],
    models: tuple[str, ...],
    runs: list[Crossval],
    got: dict[tuple[int, str], tuple[float, str]],
) -> pd.DataFrame:
    """The matrix of :func:`model_matrix` from the runs' k-fold figures (``runs``,
    :func:`run_crossval` of each item) and the held-out ones computed (``got``)."""
    n = len(models)
    errs = [
        runs[i][0][m] if m in runs[i][0] else got[(i, m)] for i in range(len(items)) for m in models
    ]
    out = pd.DataFrame(
        {
            "robot_id": [it.robot_id for it in items for _ in models],
            "recording": [it.name for it in items for _ in models],
            "model": list(models) * len(items),
            "heldout_mm": np.array([e for e, _ in errs], dtype=float),
        }
    )
    # per recording: 1 = the lowest held-out error, NaN kept (as Series.rank of each)
    ranks = out.groupby(np.repeat(np.arange(len(items)), n), sort=False)["heldout_mm"].rank(
        method="min", na_option="keep"
    )
    r = np.array(ranks, dtype=float)
    for i, (_, chosen, tied) in enumerate(runs):
        if not chosen:
            continue
        sl = r[i * n : (i + 1) * n]
        at = {m: k for k, m in enumerate(models)}
        group = [at[m] for m in [chosen, *tied] if m in at and np.isfinite(sl[at[m]])]
        if chosen in at and at[chosen] in group:  # the chosen model and those tied: one rank
            sl[group] = min(sl[k] for k in group)
    out["rank"] = [int(x) if np.isfinite(x) else -1 for x in r]
    out["note"] = [note for _, note in errs]
    return out


def run_crossval(item: AuditItem) -> Crossval:
    """The run folder's own k-fold figures: ``({model: (kfold_rms_mm, note)}, chosen,
    [models not told apart from it])``; empty where the run has no cross-validation."""
    import json

    from pipeline.io.run_folder import RUN_FILES

    try:
        s = json.loads((item.path / RUN_FILES["identify"]).read_text())
    except (OSError, ValueError):
        return {}, "", []
    cv = s.get("crossval") or {}
    out: dict[str, tuple[float, str]] = {}
    for m, v in (cv.get("models") or {}).items():
        e = v.get("kfold_rms_mm")
        if v.get("kfold_failed_folds", 1) == 0 and isinstance(e, (int, float)) and np.isfinite(e):
            out[str(m)] = (float(e), f"k-fold of the run ({cv.get('k', '?')} folds)")
    paired = cv.get("paired") or {}
    tied = [
        str(m) for m, t in paired.items() if isinstance(t, dict) and t.get("told_apart") is False
    ]
    return out, str(cv.get("chosen_model") or ""), tied


def ranking(matrix: pd.DataFrame) -> pd.DataFrame:
    """Per model: ``median_rank``, ``rms_heldout_mm`` (over the recordings every model
    fitted; when there is none, over the model's own), ``n``; best first."""
    ok = matrix["heldout_mm"].notna().groupby(matrix["recording"]).transform("all")
    full = matrix[ok] if ok.any() else matrix[matrix["heldout_mm"].notna()]
    out = []
    for m, g in matrix.groupby("model", sort=False):
        f = full[full["model"] == m]
        out.append(
            {
                "model": m,
                "median_rank": float(g.loc[g["rank"] > 0, "rank"].median()),
                "rms_heldout_mm": float(np.sqrt(np.mean(f["heldout_mm"] ** 2)))
                if len(f)
                else np.nan,
                "n": int(g["heldout_mm"].notna().sum()),
            }
        )
    return pd.DataFrame(out).sort_values(["median_rank", "rms_heldout_mm"]).reset_index(drop=True)
