"""Cross-validation: held-out error of each error model, and the choice of model by it.

Training error always favours the richer model; what a user needs is how well
a model predicts touch-ups it has not seen. Two schemes, per error model:

* **k-fold over touch-ups** (stratified by target: each target's usable
  touch-ups are shuffled and dealt round the ``k`` folds, so every target keeps
  training data). The kinematics, the pin and every target are identified on
  the other folds; a held-out touch-up ``i`` of target ``k`` scores

      e_i = T_base_flange(q_i; x_train) (p_pin,train + d_i) - t_k,train        (1)

  (``d_i`` its residual correction). A target with a single usable touch-up has
  nothing left to train on and is not scored.
* **leave one target out**: identification on every other target; the held-out
  target's position is unknown to the fit, so its touch-ups score by the spread
  of their predicted pin positions ``p_i`` (left side of (1)) about their mean,
  ``e_i = (p_i - mean p) sqrt(n / (n - 1))`` (the factor undoes the shrinkage of
  a spread about a fitted mean). Known distances involving that target drop out.

Figures are RMS over the scored touch-ups of ``|e_i|`` in mm. A held-out
residual also carries the held-out touch-up's own measurement noise; the
training fits estimate it (``3 sigma^2``, ``sigma`` the per-axis residual
scale ``sqrt(|r|^2 / dof)``), and ``kfold_model_rms_mm = sqrt(max(kfold^2 -
3 sigma^2, 0))`` estimates the error of the predicted pin position itself
(what a check against a laser tracker at touch-up-like poses would see). The model a run
ships is the one with the smallest k-fold RMS among those whose every fold
could be fitted (training RMS is reported beside it, never used to choose).
Ties within 1 % go to the model with fewer identified parameters.

What neither scheme can see: a model error that is nearly constant over one
target's poses is absorbed by that target's fitted position, in training and
held out alike (only known distances constrain it). Held-out error therefore
tracks the error against the truth where the touch-ups excite every model
direction well, and understates it where the fit leans on the target positions
(``docs/outliers.md`` has the figures).

Reference: Hastie, Tibshirani & Friedman, *The Elements of Statistical
Learning* (2nd ed.), section 7.10 (k-fold cross-validation).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.accuracy.told_apart import not_told_apart, sentence
from pipeline.errors import BadInput, CalibrationFailed
from pipeline.kinematics.se3 import F64
from pipeline.stages.crossval.predict import held_rows, joints_and_corrections, predict_pins
from pipeline.stages.crossval.predictor import predict_choice
from pipeline.stages.crossval.refit import RefitTable, refit, refit_config, refit_table
from pipeline.stages.identify.stage import IdentifyConfig
from pipeline.stages.identify.types import Robot
from pipeline.stages.parallel_map import parallel_map


@dataclass
class CrossvalConfig:
    """Cross-validation settings.

    Attributes
    ----------
    k : folds of the k-fold scheme (at most the largest target's touch-up count)
    models : error models to compare (``--set crossval.models=full,elastic``);
        empty: the identify stage's model, or, when it is ``"all"``, every registered
        model: ``calibrated.urdf`` takes the best a URDF carries exactly, predictions
        (``calibration.json``) may take one it cannot (:mod:`.predictor`)
    seed : seed of the fold assignment
    loto : also run leave-one-target-out
    workers : processes the error models are cross-validated in (each model's fits in
        one); 1 runs them in this process, 0 picks 2 when the machine has a core to spare
        (see :func:`pipeline.stages.parallel_map.parallel_map`). The results are the same;
        on this project's shared 2-core machine 2 processes were slower (load 4-6).
    """

    k: int = 5
    models: list[str] = field(default_factory=list)
    seed: int = 0
    loto: bool = True
    workers: int = 0


@dataclass
class CrossvalResult:
    """Held-out residuals (``schemas/crossval.json``), the chosen model and a JSON summary."""

    table: pd.DataFrame
    chosen_model: str | None
    summary: dict[str, Any]


def usable_rows(table: pd.DataFrame, joint_names: list[str]) -> np.ndarray:
    """Bool mask of the rows identification uses (inlier, converged, weight > 0, joints)."""
    n = len(table)
    ok = np.ones(n, dtype=bool)
    for c in ("inlier", "converged"):
        if c in table.columns:
            ok &= table[c].fillna(False).to_numpy(dtype=bool)
    if "weight" in table.columns:
        ok &= table["weight"].to_numpy(dtype=float) > 0
    ok &= np.all(np.isfinite(table[joint_names].to_numpy(dtype=float)), axis=1)
    ok &= table["target_id"].notna().to_numpy()
    return ok


def fold_assignment(targets: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """Fold index per row, stratified by target (see module docstring), (N,)."""
    fold = np.zeros(len(targets), dtype=np.int64)
    for t in sorted(set(targets.tolist())):
        idx = np.flatnonzero(targets == t)
        idx = idx[rng.permutation(len(idx))]
        off = int(rng.integers(0, k))
        fold[idx] = (off + np.arange(len(idx))) % k
    return fold


#: the columns of the held-out table (:attr:`CrossvalResult.table`)
_HELDOUT_COLUMNS = "model scheme fold touchup_id target_id n_train ex ey ez error_mm status".split()


def cross_validate(
    table: pd.DataFrame,
    urdf: str,
    base_link: str,
    flange_link: str,
    identify_config: IdentifyConfig,
    config: CrossvalConfig,
    full_fits: Mapping[str, Mapping[str, Any]] | None = None,
) -> CrossvalResult:
    """k-fold and leave-one-target-out held-out residuals per error model.

    Parameters
    ----------
    table : inliers artefact (or any touch-up table; ``inlier``/``converged`` honoured)
    urdf, base_link, flange_link : the nominal robot
    identify_config : settings of the identify stage (distances, loss, ...);
        its ``model`` picks the models when ``config.models`` is empty
    config : CrossvalConfig
    full_fits : ``{model: summary}`` of the fits on every usable touch-up with these
        settings, when the identify stage already made them (``identify.json["models"]``):
        their training RMS, parameter count and print-shape decision are taken from
        there instead of fitting again; a model without one is fitted here

    Returns
    -------
    CrossvalResult
        ``table``: one row per scored (model, scheme, touch-up) with the error
        vector (m) and its norm (mm), or why it was not scored; ``chosen_model``:
        smallest k-fold RMS; ``summary``: figures per model and ``choice``, a
        sentence saying the model was chosen by held-out error.
    """
    from pipeline.models import model_names

    robot = Robot.load(urdf, base_link, flange_link)
    names = list(robot.chain.joint_names)
    df = table.reset_index(drop=True)
    df.attrs = {}  # pandas deep-copies attrs on every operation: the folds need none
    missing = [c for c in ("touchup_id", "target_id", *names) if c not in df.columns]
    if missing:
        raise BadInput(f"touch-up table: missing column(s) {missing} for cross-validation")
    if config.models:
        models = list(config.models)
    elif identify_config.model == "all":
        models = list(model_names(robot.chain))
    else:
        models = [identify_config.model]
    base_cfg = dataclasses.replace(identify_config, n_workspace=4)
    s = _split(refit_table(df, robot, base_cfg), names, config)  # the table prepared once

    known = full_fits or {}

    def one_task(task: tuple[str, str]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        m, scheme = task
        return _validate_model(m, s, base_cfg, config.loto, known.get(m), scheme)

    # a model the identify stage fitted needs no fit of its own here: its k-fold and
    # leave-one-target-out refits are two tasks (8 of unequal cost balance two
    # processes better than 4); otherwise one task fits it once for both
    tasks = [
        (m, sch)
        for m in models
        for sch in (("kfold", "loto") if config.loto and _known(known.get(m)) else ("both",))
    ]
    # handed out longest first (a model's identify seconds times its refits), so the two
    # processes finish together; the results are put back in the order of ``tasks``
    n_tgt = len(np.unique(s.tid[s.use].astype(str)))
    refits = {"kfold": s.k, "loto": n_tgt, "both": s.k + n_tgt}
    order = sorted(range(len(tasks)), key=lambda i: -_task_cost(known, tasks[i], refits))
    done = parallel_map(one_task, [tasks[i] for i in order], config.workers, yield_to_busy=False)
    results: list[Any] = [None] * len(tasks)
    for j, i in enumerate(order):
        results[i] = done[j]
    rows: list[dict[str, Any]] = []
    summary_models: dict[str, Any] = {}
    for (m, _), (m_rows, info) in zip(tasks, results, strict=True):
        rows += m_rows  # a model's k-fold rows, then its leave-one-target-out rows
        summary_models[m] = {**summary_models.get(m, {}), **info}
    out = pd.DataFrame(rows, columns=_HELDOUT_COLUMNS)
    _figures(out, summary_models)
    trained = {m: f.get("rms_mm") for m, f in known.items() if isinstance(f, Mapping)}
    chosen, choice = _choose(summary_models, trained)
    summary = _summary(s.k, config, summary_models, chosen, choice)
    if chosen is not None:  # (T1): which models the held-out errors cannot tell apart
        summary["paired"] = not_told_apart(out, chosen, list(summary_models))
        summary["choice"] = choice + sentence(chosen, summary["paired"])
    summary["predict_model"], summary["predict_choice"] = predict_choice(
        summary_models, chosen, summary.get("paired") or {}
    )
    return CrossvalResult(table=out, chosen_model=chosen, summary=_strict(summary))


@dataclass
class _Split:
    """The touch-up table as cross-validation reads it: usable rows, folds, inputs of (1)."""

    t: RefitTable  # the table, prepared for the refits
    use: np.ndarray  # usable rows
    q_all: np.ndarray  # (n, dof) joint vectors
    d_all: np.ndarray  # (n, 3) residual corrections (0 where missing)
    tid: np.ndarray  # target ids
    tu: np.ndarray  # touch-up ids
    k: int  # folds
    fold: np.ndarray  # fold of each usable row, -1 elsewhere


def _split(t: RefitTable, names: list[str], config: CrossvalConfig) -> _Split:
    """Usable rows, ``k`` (at most the largest target's usable touch-ups) and the folds."""
    df = t.df
    use = usable_rows(df, names)
    q_all, d_all = joints_and_corrections(df, names)
    tid = df["target_id"].to_numpy()
    tu = df["touchup_id"].to_numpy(dtype=np.int64)
    _, cnt = np.unique(tid[use].astype(str), return_counts=True)
    k = int(max(2, min(config.k, int(cnt.max()) if cnt.size else 2)))
    fold = np.full(len(df), -1, dtype=np.int64)
    fold[use] = fold_assignment(tid[use], k, np.random.default_rng(config.seed))
    return _Split(t, use, q_all, d_all, tid, tu, k, fold)


def _heldout_row(
    s: _Split, model: str, scheme: str, f: int, i: int, n_train: int, e: F64 | None, why: str
) -> dict[str, Any]:
    """One row of the held-out table: touch-up ``i``'s error vector ``e`` (m), or why none."""
    return {
        "model": model,
        "scheme": scheme,
        "fold": f,
        "touchup_id": int(s.tu[i]),
        "target_id": int(s.tid[i]),
        "n_train": n_train,
        "ex": float(e[0]) if e is not None else math.nan,
        "ey": float(e[1]) if e is not None else math.nan,
        "ez": float(e[2]) if e is not None else math.nan,
        "error_mm": float(np.linalg.norm(e) * 1e3) if e is not None else math.nan,
        "status": why,
    }


def _task_cost(known: Mapping[str, Any], task: tuple[str, str], refits: dict[str, int]) -> float:
    """A task's expected cost: its model's identify seconds (1 if unknown) times its refits."""
    summary = known.get(task[0])
    sec = summary.get("seconds") if isinstance(summary, Mapping) else None
    return (float(sec) if isinstance(sec, (int, float)) else 1.0) * refits[task[1]]


def _known(known: Any) -> bool:
    """Whether ``known`` is a full fit's summary the refits can take their settings from."""
    return isinstance(known, Mapping) and {"rms_mm", "n_identified"} <= set(known)


def _validate_model(
    m: str,
    s: _Split,
    base_cfg: IdentifyConfig,
    loto: bool,
    known: Any,
    scheme: str = "both",
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Held-out rows and the summary of model ``m``: the full fit, k folds, LOTO.

    ``known`` is the identify stage's summary of the full fit, if it made one.
    ``scheme``: ``kfold`` or ``loto`` makes that scheme's rows and figures only
    (their merge is what ``both`` gives).
    """
    mcfg = dataclasses.replace(base_cfg, model=m)
    info: dict[str, Any] = {"k": s.k, "urdf_exact": _urdf_exact(m)}
    try:
        if _known(known):
            full_summary: Mapping[str, Any] = known  # the identify stage's own fit
        else:
            full_summary = refit(s.t, s.use, mcfg).summary
        info["train_rms_mm"] = float(full_summary["rms_mm"])
        info["n_identified"] = int(full_summary["n_identified"])
        mcfg = refit_config(mcfg, full_summary)
    except (BadInput, CalibrationFailed) as exc:
        info["train_rms_mm"] = math.nan
        info["error"] = str(exc)
    rows = _kfold(m, s, mcfg, info) if scheme != "loto" else []
    if scheme == "kfold":
        return rows, info
    loto_failed = 0
    if loto:
        loto_rows, loto_failed = _leave_one_target_out(m, s, mcfg)
        rows += loto_rows
    info["loto_failed_targets"] = loto_failed
    return rows, info


def _kfold(m: str, s: _Split, mcfg: IdentifyConfig, info: dict[str, Any]) -> list[dict[str, Any]]:
    """The k-fold rows of model ``m``; its failed folds and noise estimate go to ``info``."""
    pred = held_rows(s.t, s.use, s.fold, mcfg, every_row=False)
    failed = len({r["fold"] for r in pred if r["status"].startswith("fold not fitted")})
    add = functools.partial(_heldout_row, s, m, "kfold")
    rows = []
    for r in pred:
        e = None
        if not r["status"]:
            e = np.array([r["px"], r["py"], r["pz"]]) - np.array([r["tx"], r["ty"], r["tz"]])
        rows.append(add(r["fold"], r["row"], r["n_train"], e, r["status"]))
    info["kfold_failed_folds"] = failed
    sig = np.array([r["sigma_m"] for r in pred if r["status"] == ""], dtype=float)
    sig = sig[np.isfinite(sig)]
    info["kfold_noise_mm"] = float(np.sqrt(3 * np.mean(sig**2)) * 1e3) if sig.size else math.nan
    return rows


def _leave_one_target_out(
    m: str, s: _Split, mcfg: IdentifyConfig
) -> tuple[list[dict[str, Any]], int]:
    """The leave-one-target-out rows of model ``m``, and how many targets could not be fitted."""
    rows: list[dict[str, Any]] = []
    add = functools.partial(_heldout_row, s, m, "loto")
    use, tid = s.use, s.tid
    loto_failed = 0
    for f, t in enumerate(sorted(set(tid[use].tolist()))):
        held = use & (tid == t)
        train = use & (tid != t)
        hi = np.flatnonzero(held)
        if len(hi) < 2:
            for i in hi:
                rows.append(add(f, int(i), int(train.sum()), None, "single touch-up"))
            continue
        try:
            res = refit(s.t, train, mcfg)
        except (BadInput, CalibrationFailed) as exc:
            loto_failed += 1
            for i in hi:
                rows.append(add(f, int(i), int(train.sum()), None, f"not fitted: {exc}"))
            continue
        p = predict_pins(res, s.q_all[hi], s.d_all[hi])
        dev = (p - p.mean(axis=0)) * math.sqrt(len(hi) / (len(hi) - 1))
        for j, i in enumerate(hi):
            rows.append(add(f, int(i), int(train.sum()), dev[j], ""))
    return rows, loto_failed


def _figures(out: pd.DataFrame, summary_models: dict[str, Any]) -> None:
    """Per model and scheme: scored touch-ups, RMS and max (mm); the k-fold model RMS."""
    for m, info in summary_models.items():
        for scheme in ("kfold", "loto"):
            e = out[(out["model"] == m) & (out["scheme"] == scheme)]["error_mm"].dropna()
            info[f"{scheme}_n"] = int(len(e))
            info[f"{scheme}_rms_mm"] = float(np.sqrt(np.mean(e**2))) if len(e) else math.nan
            info[f"{scheme}_max_mm"] = float(e.max()) if len(e) else math.nan
        kf, nz = info["kfold_rms_mm"], info.get("kfold_noise_mm", math.nan)
        info["kfold_model_rms_mm"] = (
            float(np.sqrt(max(kf**2 - nz**2, 0.0))) if np.isfinite(kf) and np.isfinite(nz) else kf
        )


def _summary(
    k: int, config: CrossvalConfig, summary_models: dict[str, Any], chosen: str | None, choice: str
) -> dict[str, Any]:
    """The summary of the cross-validation: figures per model, the choice, what it means."""
    scored = {
        m: v["kfold_rms_mm"]
        for m, v in summary_models.items()
        if v.get("kfold_failed_folds", 1) == 0 and np.isfinite(v.get("kfold_rms_mm", math.nan))
    }
    return {
        "k": k,
        "seed": config.seed,
        "models": summary_models,
        "chosen_model": chosen,
        "best_predictor": min(scored, key=lambda m: scored[m]) if scored else None,
        "choice": choice,
        "note": (
            "held-out residual: pin position predicted by the kinematics and pin fitted "
            "without the touch-up, against its target's position fitted on the other "
            "touch-ups (k-fold); spread of a left-out target's predicted pin positions "
            "about their mean (leave one target out). Blind to model errors the fitted "
            "target positions absorb (a nearly constant offset over one target's poses): "
            "read it with the covariance-predicted error of identify"
        ),
    }


def _strict(obj: Any) -> Any:
    """JSON-safe copy: NaN and infinities become None (strict JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _strict(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_strict(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _urdf_exact(name: str) -> bool:
    """Whether the calibrated URDF of model ``name`` reproduces it (True for a rule like auto)."""
    from pipeline.models import get_model

    try:
        return bool(get_model(name).urdf_exact)
    except KeyError:
        return True


def _choose(
    models: dict[str, dict[str, Any]], trained: Mapping[str, Any] | None = None
) -> tuple[str | None, str]:
    """Smallest k-fold RMS among completely cross-validated models (ties: fewer parameters).

    ``trained``: training RMS (mm) of every fitted model, cross-validated or not; the
    sentence names the training choice only when it beats the chosen one by over 1 %.

    A model whose URDF cannot carry it (``urdf_exact`` false, e.g. ``elastic``) is
    never chosen over one whose URDF can: the chosen model becomes
    ``calibrated.urdf``, and its rigid part alone may predict worse than a rigid
    model. When it predicts best, the sentence says so, with both figures.
    """
    complete = {
        m: v
        for m, v in models.items()
        if v.get("kfold_failed_folds", 1) == 0 and np.isfinite(v.get("kfold_rms_mm", math.nan))
    }
    exact = {m: v for m, v in complete.items() if v.get("urdf_exact", True)}
    ok = exact or complete
    best_any = min(complete, key=lambda m: complete[m]["kfold_rms_mm"]) if complete else None
    if not ok:
        return None, (
            "no error model could be cross-validated on every fold: none chosen by held-out "
            "error (calibrated.urdf stays the identify stage's)"
        )
    best = min(v["kfold_rms_mm"] for v in ok.values())
    near = [m for m, v in ok.items() if v["kfold_rms_mm"] <= best * 1.01]
    chosen = min(near, key=lambda m: (ok[m].get("n_identified", 0), ok[m]["kfold_rms_mm"]))
    v = ok[chosen]
    text = (
        f"error model chosen by held-out (k-fold cross-validation) error, not training error: "
        f"{chosen}, held-out RMS {v['kfold_rms_mm']:.4f} mm (training RMS "
        f"{v.get('train_rms_mm', math.nan):.4f} mm)"
    )
    if len(models) > 1:
        train = {m: v.get("train_rms_mm", math.nan) for m, v in models.items()}
        train.update({m: t for m, t in (trained or {}).items() if isinstance(t, (int, float))})
        finite = {m: float(t) for m, t in train.items() if np.isfinite(t)}
        own = finite.get(chosen, math.nan)
        if finite and np.isfinite(own):
            by_train = min(finite, key=lambda m: finite[m])
            if finite[by_train] * 1.01 < own:
                note = "" if by_train in models else ", not cross-validated"
                text += (
                    f"; the smallest training RMS ({by_train}, {finite[by_train]:.4f} mm"
                    f"{note}) would have chosen differently"
                )
            else:
                text += "; the smallest training RMS would have chosen the same"
    else:
        text += "; only one model was cross-validated"
    if best_any is not None and best_any != chosen and not models[best_any].get("urdf_exact", True):
        b = models[best_any]
        text += (
            f"; {best_any} predicts held-out touch-ups better ({b['kfold_rms_mm']:.4f} mm) but a "
            "URDF cannot carry its configuration-dependent terms, so calibrated.urdf is "
            f"{chosen}'s; {best_any}'s values are in parameters.parquet (calibration.json "
            "carries the model predictions use)"
        )
    if not v.get("urdf_exact", True):
        text += (
            f"; calibrated.urdf holds only {chosen}'s rigid part (a URDF cannot carry the rest): "
            "use its parameters.parquet values to predict as it does"
        )
    return chosen, text
