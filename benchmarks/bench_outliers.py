"""Outlier rejection, knock splitting and cross-validation against simulator truth.

For each seed the standard cell (``datasets/scenarios/standard.toml``: 3 targets
x 12 poses, calibration bar) is simulated three times with the same seed: with
every fault the simulator offers switched on (``[faults]`` all true), with every
fault but the knock, and with none. The simulator adds touch-up faults as extra
touch-ups and draws each touch-up's noise from its own stream, so the fault-free
recording's touch-ups are in the others bit for bit (``docs/simulator.md``). All
go through ``vtcal run --until crossval --model all``. Printed, per seed and in
total:

* every injected fault and whether the pipeline flagged it with the right reason
  (touch-up faults: the inliers ``reason``; a knock: the split at the right
  touch-up; faults on images that were not averaged at the final pose: the
  frames/detections artefacts flag the image and the touch-up rightly stays);
* good touch-ups rejected (rows no injected fault touches, ``inlier`` false);
* the knocked target's two fitted positions: their distance against the truth's
  ``|shift_m|``;
* final accuracy (absolute, rigid registration over 300 poses spread through the
  touched volume) of ``calibrated.urdf`` with faults against without: ratio;
  also with every fault but the knock, and that recording without its extra
  faulted touch-ups (the fault-free recording's touch-ups, judged by the truth),
  and the faulty recording with the truth's verdicts instead of the stage's;
* the chosen model's k-fold held-out RMS against the same held-out touch-ups
  measured with the truth: each fold's model registered to the true robot, its
  predicted pin against the true target centre (ratio); and, apart, against the
  true pin (the model's error alone, without the touch-up's own noise).

    python benchmarks/bench_outliers.py [--seeds 1 2 3] [--work DIR] [--scenario TOML]

Simulations are cached in ``--work`` (default
``/tmp/vtcal_bench_outliers``; delete it to start afresh); the runs are redone
(``--force``) every time. One core, about a minute per seed the first time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.accuracy.evaluate import pin_accuracy, register_points, workspace_poses
from pipeline.io.known_distances import parse_distances
from pipeline.kinematics.chain import fk, load_chain
from pipeline.stages.crossval.predict import heldout_predictions
from pipeline.stages.crossval.stage import fold_assignment, usable_rows
from pipeline.stages.identify.stage import IdentifyConfig

ROOT = Path(__file__).resolve().parent.parent
FAULTS = (
    "capture_while_moving",
    "second_blob",
    "unconverged",
    "knocked_target",
    "joint_state_gap",
    "lost_target",
    "truncate",
)


def _toml(d: dict[str, Any]) -> str:
    lines: list[str] = []
    for k, v in d.items():
        if not isinstance(v, dict):
            lines.append(f"{k} = {json.dumps(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {json.dumps(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def scenarios(src: Path, work: Path) -> tuple[Path, Path, Path]:
    """The scenario with every fault on, with every fault but the knock, and with none."""
    base = tomllib.loads(src.read_text())
    out = []
    for tag, on in (("faults", set(FAULTS)), ("noknock", set(FAULTS) - {"knocked_target"}),
                    ("clean", set())):  # fmt: skip
        sc = dict(base)
        sc["name"] = f"{base.get('name', 'bench')}_{tag}"
        sc["faults"] = {f: f in on for f in FAULTS}
        p = work / f"{sc['name']}.toml"
        p.write_text(_toml(sc))
        out.append(p)
    return out[0], out[1], out[2]


def sh(*args: str) -> None:
    subprocess.run(
        [sys.executable, "-m", "pipeline", *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL
    )


def simulate_and_run(scenario: Path, seed: int, work: Path) -> tuple[Path, dict[str, Any]]:
    rec = work / f"{scenario.stem}_s{seed}.mcap"
    if not Path(str(rec) + ".truth.json").exists():
        sh(
            "simulate",
            "--scenario",
            str(scenario),
            "--seed",
            str(seed),
            "--out",
            str(rec),
            "--quiet",
        )
    run = work / f"run_{scenario.stem}_s{seed}"
    args = ("--until", "crossval", "--model", "all", "-q", "--force")
    sh("run", str(rec), "--out", str(run), *args)
    return run, json.loads(Path(str(rec) + ".truth.json").read_text())


def _frames_of(tu: pd.DataFrame, img: int) -> tuple[int | None, bool]:
    """(touch-up id holding image ``img``, whether it was averaged at the final pose)."""
    ids = tu["touchup_id"].to_numpy(dtype=np.int64)
    for i, (fr, conv) in enumerate(
        zip(tu["frame_indices"].tolist(), tu["converged_frame_indices"].tolist(), strict=True)
    ):
        if img in [int(v) for v in fr]:
            return int(ids[i]), img in [int(v) for v in conv]
    return None, False


def fault_recall(run: Path, truth: dict[str, Any]) -> tuple[list[dict[str, Any]], set[int]]:
    """One verdict per injected fault, and the touch-up ids a fault made bad."""
    inl = pd.read_parquet(run / "inliers.parquet")
    tu = pd.read_parquet(run / "touchups.parquet")
    frames = pd.read_parquet(run / "frames.parquet").set_index("frame_index")
    det = pd.read_parquet(run / "detections.parquet").set_index("frame_index")
    rec = json.loads((run / "recording.json").read_text())
    reason = dict(zip(inl["touchup_id"], inl["reason"].astype(str), strict=True))
    bad: set[int] = set()
    out = []
    for f in truth["faults"]:
        typ = f["type"]
        t = f.get("touchup")
        ok: bool | None = False
        how = ""
        if typ == "unconverged":
            ok = "not converged" in reason.get(t, "")
            how = f"touch-up {t}: {reason.get(t, 'absent')!r}"
            bad.add(t)
        elif typ == "target_lost":
            ok = "target lost" in reason.get(t, "")
            how = f"touch-up {t}: {reason.get(t, 'absent')!r}"
            bad.add(t)
        elif typ == "target_knocked":
            after = set(f["touchups_after"])
            rows = inl[inl["source_target_id"] == f["label"]]
            moved = rows[rows["target_id"] != rows["source_target_id"]]
            usable_after = set(
                rows[rows["touchup_id"].isin(after) & (rows["reason"] == "")]["touchup_id"]
            )
            got = set(moved["touchup_id"])
            ok = usable_after <= got and got <= after
            how = f"after-knock touch-ups {sorted(after)}, split off {sorted(got)}"
        elif typ in ("capture_while_moving", "second_blob", "target_cut_by_border"):
            verdicts = []
            for img in f["image_indices"]:
                tid, averaged = _frames_of(tu, img)
                if img not in frames.index:
                    verdicts.append(False)
                    continue
                if typ == "capture_while_moving":
                    seen = bool(frames.loc[img, "moving"])
                    rule = "captured while moving"
                elif typ == "second_blob":
                    seen = int(det.loc[img, "n_blobs"]) > 1 or bool(det.loc[img, "ambiguous"])
                    rule = "ambiguous blob"
                else:
                    seen = bool(det.loc[img, "border_contact"])
                    rule = "contour cut by the border"
                wrong_blob = typ == "second_blob" and bool(det.loc[img, "ambiguous"])
                if averaged and (typ != "second_blob" or wrong_blob):
                    # the image entered the touch-up's result: it must be rejected
                    verdicts.append(tid is not None and rule in reason.get(tid, ""))
                    if tid is not None:
                        bad.add(tid)
                else:
                    verdicts.append(seen)
            ok = all(verdicts)
            how = f"images {f['image_indices']}: frame-level flags {verdicts}"
        elif typ == "joint_state_gap":
            lo, hi = f["missing_stamps_ns"]
            st = frames["stamp_ns"].to_numpy()
            hit = frames.index[(st >= lo) & (st <= hi)].tolist()
            warned = any("gap" in w.lower() for w in rec.get("warnings", []))
            if hit:
                ok = bool(frames.loc[hit, "joint_gap"].all()) and warned
                how = f"images in the gap: {hit}; ingest warning: {warned}"
            else:
                ok = None  # nothing the gap touches: no verdict
                how = "no image in the gap (it fell in a move): nothing to flag"
        elif typ == "truncated_file":
            ok = bool(rec.get("truncated"))
            how = f"recording.json truncated={rec.get('truncated')}"
        else:
            how = "unknown fault type"
        out.append({"type": typ, "touchup": t, "flagged": ok, "how": how})  # ok None: no effect
    return out, bad


def accuracy(run: Path, truth: dict[str, Any], model: str | None = None) -> dict[str, float]:
    """Pin accuracy of the run's calibrated.urdf (or calibrated_MODEL.urdf) against the truth."""
    name = f"calibrated_{model}.urdf" if model else "calibrated.urdf"
    cal = load_chain((run / name).read_text(), truth["base_link"], "virtual_pin")
    true_chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    inl = pd.read_parquet(run / "inliers.parquet")
    ok = inl["inlier"].to_numpy(dtype=bool)
    q = workspace_poses(inl.loc[ok, truth["joint_names"]].to_numpy(), 300, np.random.default_rng(0))
    return pin_accuracy(cal, np.zeros(3), true_chain, np.array(truth["p_vt_flange"]), q)


def refit_accuracy(
    rec: dict[str, Any], table: pd.DataFrame, model: str, truth: dict[str, Any], poses: pd.DataFrame
) -> dict[str, float]:
    """Identify ``table`` (inliers layout) with ``model`` and the recording's known
    distances, then judge it as :func:`accuracy` does, over the volume of the inlier
    touch-ups of ``poses``."""
    from pipeline.stages.identify.stage import IdentifyResult, identify

    cfg = IdentifyConfig(
        model=model, distances=parse_distances(rec["metadata"].get("known_distances", ""))
    )
    res = identify(table, rec["urdf"], rec["base_link"], rec["flange_link"], cfg)
    assert isinstance(res, IdentifyResult)
    true_chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    ok = poses["inlier"].to_numpy(dtype=bool)
    q = workspace_poses(
        poses.loc[ok, truth["joint_names"]].to_numpy(), 300, np.random.default_rng(0)
    )
    return pin_accuracy(res.chain, res.p_flange_pin, true_chain, np.array(truth["p_vt_flange"]), q)


def oracle_accuracy(run: Path, truth: dict[str, Any], bad: set[int]) -> dict[str, float]:
    """Accuracy of the same recording with the truth's own verdicts instead of the stage's.

    The touch-ups a fault made bad are left out and the knocked target is split
    exactly where the truth says; identification as in the run (shipped model,
    known distances). Against this, the stage's accuracy shows what its decisions
    cost, free of the noise draws that differ between two recordings.
    """
    rec = json.loads((run / "recording.json").read_text())
    summ = json.loads((run / "identify.json").read_text())
    inl = pd.read_parquet(run / "inliers.parquet")
    t = inl.copy()
    t["target_id"] = t["source_target_id"]
    t["inlier"] = ~t["touchup_id"].isin(bad) & t["converged"].astype(bool)
    label = int(t["target_id"].max()) + 1
    for f in truth["faults"]:
        if f["type"] == "target_knocked":
            t.loc[t["touchup_id"].isin(f["touchups_after"]), "target_id"] = label
            label += 1
    return refit_accuracy(rec, t, summ["best_model"], truth, inl)


def same_touchups_accuracy(run: Path, truth: dict[str, Any], clean_run: Path) -> dict[str, float]:
    """Accuracy of ``run`` without its extra, faulted touch-ups, model of ``clean_run``.

    The simulator adds every touch-up fault as an extra touch-up (docs/simulator.md),
    so leaving those out (by the truth) leaves the touch-ups of the fault-free twin;
    identification as in ``clean_run`` (its shipped model, known distances), judged
    as :func:`accuracy` judges ``clean_run``.
    """
    rec = json.loads((run / "recording.json").read_text())
    extra = {f["touchup"] for f in truth["faults"] if "touchup" in f}
    t = pd.read_parquet(run / "inliers.parquet")
    t["inlier"] = ~t["touchup_id"].isin(extra) & t["inlier"].astype(bool)
    model = json.loads((clean_run / "identify.json").read_text())["best_model"]
    return refit_accuracy(rec, t, model, truth, pd.read_parquet(clean_run / "inliers.parquet"))


def knock_distance(run: Path, truth: dict[str, Any]) -> tuple[float, float] | None:
    knocks = [f for f in truth["faults"] if f["type"] == "target_knocked"]
    if not knocks:
        return None
    f = knocks[0]
    inl = pd.read_parquet(run / "inliers.parquet")
    rows = inl[(inl["source_target_id"] == f["label"]) & (inl["target_id"] != f["label"])]
    if not len(rows):
        return float("nan"), float(np.linalg.norm(f["shift_m"]))
    new = int(rows["target_id"].iloc[0])
    summ = json.loads((run / "identify.json").read_text())
    tg = pd.read_parquet(run / "targets.parquet")
    tg = tg[tg["model"] == summ["best_model"]].set_index("target_id")
    if new not in tg.index or f["label"] not in tg.index:
        return float("nan"), float(np.linalg.norm(f["shift_m"]))
    a = tg.loc[f["label"], ["x", "y", "z"]].to_numpy(dtype=float)
    b = tg.loc[new, ["x", "y", "z"]].to_numpy(dtype=float)
    return float(np.linalg.norm(a - b)), float(np.linalg.norm(f["shift_m"]))


def heldout_truth(
    run: Path, truth: dict[str, Any], model: str, k: int, seed: int
) -> tuple[float, float]:
    """RMS errors against the truth of each k-fold model at its held-out touch-ups, m.

    The same folds as the crossval stage; each fold's model is registered to the
    truth (one rigid motion, over every usable touch-up pose: the accuracy
    definition of ``spec/outputs.md``) and judged at its held-out
    touch-ups in two ways:

    * against the true target centre the touch-up touched: the error the model makes
      predicting a touch-up it has not seen, measured with the truth instead of a
      fitted target (what k-fold cross-validation estimates; the held-out
      touch-up's own noise is in both);
    * against the true pin at the recorded joints (with the touch-up's correction
      ``d``): the model's error alone, free of the touch-up's noise.

    Returns
    -------
    (RMS against the true target centres, RMS against the true pin), m.
    """
    rec = json.loads((run / "recording.json").read_text())
    inl = pd.read_parquet(run / "inliers.parquet")
    names = truth["joint_names"]
    use = usable_rows(inl, names)
    fold = np.full(len(inl), -1, dtype=np.int64)
    fold[use] = fold_assignment(inl["target_id"].to_numpy()[use], k, np.random.default_rng(seed))
    cfg = IdentifyConfig(
        model=model, distances=parse_distances(rec["metadata"].get("known_distances", ""))
    )
    pr = heldout_predictions(
        inl, use, fold, rec["urdf"], rec["base_link"], rec["flange_link"], cfg, every_row=True
    )
    pr = pr[pr["status"] == ""]
    tc = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    q_all = inl[names].to_numpy(dtype=float)
    d_all = inl[["dx_flange", "dy_flange", "dz_flange"]].to_numpy(dtype=float)
    pin = np.asarray(truth["p_vt_flange"], dtype=float)
    centre = {
        int(t["index"]): np.asarray(t["target_centre"], dtype=float) for t in truth["touchups"]
    }
    ids = inl["touchup_id"].to_numpy(dtype=np.int64)
    errs: list[float] = []
    errs_target: list[float] = []
    for _, g in pr.groupby("fold"):
        rows = g["row"].to_numpy(dtype=np.int64)
        T = fk(tc, q_all[rows])
        p_true = np.einsum("nij,nj->ni", T[:, :3, :3], pin[None] + d_all[rows]) + T[:, :3, 3]
        p_model = g[["px", "py", "pz"]].to_numpy(dtype=float)
        R, t, _ = register_points(p_model, p_true, scale=False)
        p_reg = p_model @ R.T + t
        held = g["held"].to_numpy(dtype=bool)
        errs += np.linalg.norm(p_reg - p_true, axis=1)[held].tolist()
        c_true = np.stack([centre[int(i)] for i in ids[rows]])
        errs_target += np.linalg.norm(p_reg - c_true, axis=1)[held].tolist()
    return (
        float(np.sqrt(np.mean(np.square(errs_target)))),
        float(np.sqrt(np.mean(np.square(errs)))),
    )


def judge_recording(rec: Path, work: Path) -> None:
    """Fault recall and good rejected on one recording with a truth file beside it."""
    truth = json.loads(Path(str(rec) + ".truth.json").read_text())
    run = work / f"run_{rec.stem}"
    sh("run", str(rec), "--out", str(run), "--until", "crossval", "-q", "--force")
    verdicts, bad = fault_recall(run, truth)
    print(f"== {rec.name}")
    for v in verdicts:
        tag = {True: "FLAGGED", False: "MISSED ", None: "NO-EFFECT"}[v["flagged"]]
        print(f"  {tag:9s} {v['type']:22s} {v['how']}")
    inl = pd.read_parquet(run / "inliers.parquet")
    good = inl[~inl["touchup_id"].isin(bad)]
    print(f"  good touch-ups rejected: {int((~good['inlier']).sum())}/{len(good)}")
    kd = knock_distance(run, truth)
    if kd:
        print(f"  knocked target: fitted distance {kd[0] * 1e3:.3f} mm, truth {kd[1] * 1e3:.3f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--work", type=Path, default=Path("/tmp/vtcal_bench_outliers"))
    ap.add_argument("--scenario", type=Path, default=ROOT / "datasets/scenarios/standard.toml")
    ap.add_argument("--recording", type=Path, default=None,
                    help="Judge one recording with a truth file instead (e.g. the conformance "
                    "sample): fault recall, good rejected, knock distance.")  # fmt: skip
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    if a.recording is not None:
        judge_recording(a.recording, a.work)
        return
    sc_on, sc_nk, sc_off = scenarios(a.scenario, a.work)
    nk_ratios: list[float] = []
    same_ratios: list[float] = []
    n_faults = n_flagged = n_good = n_good_rej = n_no_effect = 0
    acc_ratios, cv_ratios, knock, oracle_ratios, raw_ratios = [], [], [], [], []
    tt_ratios: list[float] = []
    for seed in a.seeds:
        run_f, truth_f = simulate_and_run(sc_on, seed, a.work)
        run_c, truth_c = simulate_and_run(sc_off, seed, a.work)
        run_nk, truth_nk = simulate_and_run(sc_nk, seed, a.work)
        verdicts, bad = fault_recall(run_f, truth_f)
        print(f"\n== seed {seed}: {run_f.name}")
        for v in verdicts:
            tag = {True: "FLAGGED", False: "MISSED ", None: "NO-EFFECT"}[v["flagged"]]
            print(f"  {tag:9s} {v['type']:22s} {v['how']}")
        n_faults += sum(v["flagged"] is not None for v in verdicts)
        n_flagged += sum(v["flagged"] is True for v in verdicts)
        n_no_effect += sum(v["flagged"] is None for v in verdicts)
        inl = pd.read_parquet(run_f / "inliers.parquet")
        good = inl[~inl["touchup_id"].isin(bad)]
        rej = good[~good["inlier"]]
        n_good += len(good)
        n_good_rej += len(rej)
        for r in rej.itertuples():
            print(f"  good touch-up rejected: {r.touchup_id} ({r.reason})")
        inl_c = pd.read_parquet(run_c / "inliers.parquet")
        rej_c = inl_c[~inl_c["inlier"]]
        n_good += len(inl_c)
        n_good_rej += len(rej_c)
        for r in rej_c.itertuples():
            print(f"  clean recording, touch-up rejected: {r.touchup_id} ({r.reason})")
        kd = knock_distance(run_f, truth_f)
        if kd:
            knock.append(kd)
            print(
                f"  knocked target: fitted distance {kd[0] * 1e3:.3f} mm, truth shift "
                f"{kd[1] * 1e3:.3f} mm (error {abs(kd[0] - kd[1]) * 1e3:.3f} mm)"
            )
        af, ac = accuracy(run_f, truth_f), accuracy(run_c, truth_c)
        ao = oracle_accuracy(run_f, truth_f, bad)
        ratio = af["abs_rms_m"] / ac["abs_rms_m"]
        acc_ratios.append(ratio)
        ank = accuracy(run_nk, truth_nk)
        nk_ratios.append(ank["abs_rms_m"] / ac["abs_rms_m"])
        asame = same_touchups_accuracy(run_nk, truth_nk, run_c)
        same_ratios.append(asame["abs_rms_m"] / ac["abs_rms_m"])
        print(
            f"  every fault but the knock: accuracy {ank['abs_rms_m'] * 1e3:.4f} mm, ratio to "
            f"the clean recording {nk_ratios[-1]:.3f}; without the extra faulted touch-ups "
            f"(the clean recording's touch-ups) {asame['abs_rms_m'] * 1e3:.4f} mm, ratio "
            f"{same_ratios[-1]:.3f}"
        )
        oracle_ratios.append(af["abs_rms_m"] / ao["abs_rms_m"])
        print(
            f"  accuracy (absolute RMS over 300 poses): faults {af['abs_rms_m'] * 1e3:.4f} mm, "
            f"clean recording {ac['abs_rms_m'] * 1e3:.4f} mm (ratio {ratio:.3f}); same "
            f"recording with the truth's verdicts {ao['abs_rms_m'] * 1e3:.4f} mm (ratio "
            f"{oracle_ratios[-1]:.3f})"
        )
        for run, truth, label in ((run_f, truth_f, "faults"), (run_c, truth_c, "clean")):
            summ = json.loads((run / "identify.json").read_text())
            cv = summ.get("crossval", {})
            m = cv.get("chosen_model") or summ["best_model"]
            kf = cv["models"][m]["kfold_rms_mm"]
            km = cv["models"][m].get("kfold_model_rms_mm", kf)
            lo = cv["models"][m].get("loto_rms_mm")
            tr = accuracy(run, truth, m)
            ht_target, ht = heldout_truth(run, truth, m, int(cv["k"]), int(cv["seed"]))
            tt_ratios.append(kf / (ht_target * 1e3))
            r = km / (ht * 1e3)
            cv_ratios.append(r)
            raw_ratios.append(kf / (ht * 1e3))
            print(
                f"  [{label}] chosen model {m}: k-fold held-out RMS {kf:.4f} mm; truth at the "
                f"held-out touch-ups (true target centres) {ht_target * 1e3:.4f} mm -> ratio "
                f"{tt_ratios[-1]:.2f}"
            )
            print(
                f"      model error alone: k-fold without the touch-up noise {km:.4f} mm "
                f"(leave-one-target-out {lo:.4f} mm, training "
                f"{cv['models'][m]['train_rms_mm']:.4f} mm); true pin at the held-out poses "
                f"{ht * 1e3:.4f} mm -> ratios {r:.2f} (noise removed), {raw_ratios[-1]:.2f} (raw); "
                f"truth over the volume {tr['abs_rms_m'] * 1e3:.4f} mm -> ratio "
                f"{km / (tr['abs_rms_m'] * 1e3):.2f}"
            )
    print("\n== totals")
    print(f"faults flagged with the right reason: {n_flagged}/{n_faults} "
          f"({100 * n_flagged / max(n_faults, 1):.1f} %); {n_no_effect} had no effect "
          "on any image (a joint-state gap inside a move)")  # fmt: skip
    print(f"good touch-ups rejected: {n_good_rej}/{n_good} "
          f"({100 * n_good_rej / max(n_good, 1):.2f} %)")  # fmt: skip
    if knock:
        err = [abs(a - b) / b for a, b in knock if np.isfinite(a)]
        print(f"knock distance relative error: max {100 * max(err, default=np.nan):.1f} % "
              f"over {len(err)}/{len(knock)} split targets")  # fmt: skip
    for what, rs in (
        ("every fault", acc_ratios),
        ("every fault but the knock", nk_ratios),
        ("every fault but the knock, extra faulted touch-ups left out", same_ratios),
    ):
        within = sum(abs(r - 1) <= 0.1 for r in rs)
        print(f"accuracy with {what} / clean recording (same seed): "
              f"{', '.join(f'{r:.3f}' for r in rs)} ({within}/{len(rs)} within 10 %)")  # fmt: skip
    print(f"accuracy with the stage's verdicts / with the truth's verdicts (same recording): "
          f"{', '.join(f'{r:.3f}' for r in oracle_ratios)} "
          f"(max {max(oracle_ratios):.3f})")  # fmt: skip
    within = sum(abs(r - 1) <= 0.3 for r in tt_ratios)
    print(
        "k-fold held-out RMS / truth at the held-out touch-ups (true target centres): "
        f"{', '.join(f'{r:.2f}' for r in tt_ratios)} ({within}/{len(tt_ratios)} within 30 %)"
    )
    for name, rs in (("noise removed", cv_ratios), ("raw", raw_ratios)):
        within = sum(abs(r - 1) <= 0.3 for r in rs)
        print(
            f"model error alone: k-fold held-out RMS ({name}) / true pin at the held-out poses: "
            f"{', '.join(f'{r:.2f}' for r in rs)} ({within}/{len(rs)} within 30 %)"
        )


if __name__ == "__main__":
    main()
