"""Which error model predicts best across the fleet: a models x recordings matrix.

Per recording and error model, the two-fold held-out consistency
(:func:`pipeline.audit.fit.heldout_mm`: fitted on every other touch-up of each
target, judged on the rest, and the other way round). Per recording the models
are ranked (1 = lowest held-out error); overall, by the median of their ranks,
then by the RMS of their held-out errors over the recordings where every model
could be fitted.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.audit.fit import heldout_mm
from pipeline.audit.identity import AuditItem

#: the error models compared by default
MODELS = ("offsets", "mdh", "full", "poe")


def model_matrix(
    items: list[AuditItem], models: tuple[str, ...] = MODELS, workers: int = 1
) -> pd.DataFrame:
    """One row per (recording, model): ``robot_id, recording, model, heldout_mm, rank, note``.

    ``workers``: processes for the fits (:func:`pipeline.stages.parallel_map.parallel_map`;
    0 = the free cores), one task per (recording, model); the results are the serial map's.
    """
    from pipeline.stages.parallel_map import parallel_map

    tasks = [(i, m) for i in range(len(items)) for m in models]
    res = parallel_map(lambda t: heldout_mm(items[t[0]], t[1]), tasks, workers)
    got = dict(zip(tasks, res, strict=True))
    rows = []
    for i, it in enumerate(items):
        errs = {m: got[(i, m)] for m in models}
        vals = pd.Series({m: e for m, (e, _) in errs.items()})
        ranks = vals.rank(method="min", na_option="keep")
        for m, (e, note) in errs.items():
            r = ranks[m]
            rows.append(
                {
                    "robot_id": it.robot_id,
                    "recording": it.name,
                    "model": m,
                    "heldout_mm": e,
                    "rank": int(r) if np.isfinite(r) else -1,
                    "note": note,
                }
            )
    return pd.DataFrame(rows)


def ranking(matrix: pd.DataFrame) -> pd.DataFrame:
    """Per model: ``median_rank``, ``rms_heldout_mm`` (over the recordings every model
    fitted; when there is none, over the model's own), ``n``; best first."""
    ok = matrix.groupby("recording")["heldout_mm"].transform(lambda s: s.notna().all())
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
