"""Real robots: vtcal against MUKCa on real Franka Panda point-constraint data.

Data: ``datasets/real/mukca/`` (see ``datasets/real/README.md``): a ball fixed
to the Panda's hand seated by hand in two sockets 50 mm apart on a tool put at
4-9 placements; ~30 configurations per socket.

For each dataset, vtcal is trained with ``vtcal identify`` exactly as a user
calls it (the click command, in process) on the touch-ups of the training
placement only::

    vtcal identify TRAIN.csv --urdf nominal_panda.urdf --out DIR \
        --flange-link panda_hand_tcp --distance P/hole_0:P/hole_1=0.05 [--model M]

and judged on every OTHER placement with two KPIs that need no ground truth
and are invariant to the base frame (``x_i`` the pin position the model
predicts for configuration ``q_i``):

* consistency ``sqrt(mean_i |x_i - mean_s|^2)`` pooled over both sockets (mm);
* distance error ``| |mean_0 - mean_1| - 50 mm |`` (mm).

Compared: the nominal robot with the pin of the nominal URDF's ``ball_joint``,
the nominal robot with the pin refitted on the training placement (linear
least squares of the pin and the two sockets at fixed kinematics), MUKCa's
calibrated URDF of the dataset with its own ``ball_joint`` pin and with the pin
refitted the same way, and every vtcal model (``--model`` full, mdh, poe,
offsets, each registered model, and the shipped default). A model a URDF cannot
carry (the elastic ones) is judged by its own forward map with the values of its
``parameters.parquet``, and its ``calibrated.urdf`` (the rigid part) alone on a
second line. ``elastic_inertial`` needs the URDF's link inertials: it is trained
on ``nominal_panda_inertial.urdf`` (the same kinematics plus Gaz et al. 2019's
masses, see ``datasets/real/README.md``), every other model on
``nominal_panda.urdf``. Then the same with
TWO training placements (the named one and the one farthest from it), judged
on the rest.

Each split also prints the mass-model choice of the elastic error model
(``elastic``, ``elastic_mid``, ``elastic_inertial``, with ``full`` for
reference): per candidate its k-fold held-out RMS on the *training* touch-ups
(:func:`pipeline.stages.crossval.stage.cross_validate`, 5 folds, no
leave-one-target-out; what a run can judge by) next to its held-out-placement
consistency (what it should be judged by, unseen by the run), and which
candidate each picks.

    python benchmarks/bench_real.py                  # all three datasets
    python benchmarks/bench_real.py --datasets panda_3 --models default
    python benchmarks/bench_real.py --no-two         # one training placement only
    python benchmarks/bench_real.py --floors         # also: what more data buys (below)

``--floors`` asks how far a model of each kind can get on a held-out placement at
all, with the two figures the goal (20 % below MUKCa) is judged against. Per held-out
placement ``p`` of the named split and per model (``full``, ``elastic``):

* **trained on every other placement** (``vtcal identify`` on all placements but
  ``p``, 3-8 times the named split's data) and judged on ``p``: what the same
  model gets from all the data there is, not from one placement;
* **fitted on ``p`` itself** (trained and judged on the same touch-ups): an
  in-sample figure, below what any held-out figure of that model can be expected
  to reach.

Printed with their means over the held-out placements, next to the goal (80 % of
MUKCa's held-out mean).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from click.testing import CliRunner

from pipeline.kinematics import load_chain
from pipeline.kinematics.chain import Chain, fk
from pipeline.measurement.pin import fit_pin_and_targets

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "datasets" / "real" / "mukca"
DATASETS = ("panda_2", "panda_3", "panda_4")
#: the placement MUKCa trained each dataset on (datasets/real/README.md)
TRAIN = {"panda_2": "front_center", "panda_3": "frontcenter", "panda_4": "front"}
BASE, TCP = "panda_link0", "panda_hand_tcp"
JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
DISTANCE_M = 0.05
#: the models benchmarked by name; "default" is ``vtcal identify`` without --model
BASE_MODELS = ("full", "mdh", "poe", "offsets")
#: the nominal URDF with link inertials (Gaz et al. 2019), for the models that need them
INERTIAL_URDF = "nominal_panda_inertial.urdf"
#: the candidates of the elastic model's mass-model choice (and ``full`` for reference)
MASS_CANDIDATES = ("full", "elastic", "elastic_mid", "elastic_inertial")


def nominal_urdf(model: str) -> Path:
    """The nominal URDF ``model`` is trained on: with inertials where it needs them."""
    return DATA / (INERTIAL_URDF if model == "elastic_inertial" else "nominal_panda.urdf")


@dataclass(frozen=True)
class Kpi:
    consistency_mm: float
    distance_error_mm: float


def load_table(dataset: str) -> pd.DataFrame:
    """A dataset's touch-up table with a ``placement`` column."""
    df = pd.read_csv(DATA / f"{dataset}.csv")
    df["placement"] = df["target_id"].str.split("/").str[0]
    return df


def placements(df: pd.DataFrame) -> list[str]:
    return list(dict.fromkeys(df["placement"]))


def kpis(points: np.ndarray, socket: np.ndarray) -> Kpi:
    """The README's two KPIs of one placement's predicted pin positions (m in, mm out)."""
    means = {}
    sq = []
    for s in np.unique(socket):
        p = points[socket == s]
        means[s] = p.mean(axis=0)
        sq.append(np.sum((p - means[s]) ** 2, axis=1))
    cons = float(np.sqrt(np.mean(np.concatenate(sq))))
    m = list(means.values())
    dist = float(abs(np.linalg.norm(m[0] - m[1]) - DISTANCE_M))
    return Kpi(cons * 1e3, dist * 1e3)


def pin_points(chain: Chain, pin: np.ndarray, q: np.ndarray) -> np.ndarray:
    T = fk(chain, q)
    return np.einsum("nij,j->ni", T[:, :3, :3], pin) + T[:, :3, 3]


def refit_pin(chain: Chain, q: np.ndarray, socket_index: np.ndarray) -> np.ndarray:
    """Linear least squares of the pin and the sockets at fixed kinematics (no distance row)."""
    K = int(socket_index.max()) + 1
    return fit_pin_and_targets(chain, q, np.zeros((len(q), 3)), socket_index, K)[0]


def ball_pin(urdf: str) -> np.ndarray:
    """The ``ball_joint`` origin (the ball in the ``panda_hand_tcp`` frame) of a URDF."""
    root = ET.fromstring(urdf)
    for j in root.findall("joint"):
        if j.get("name") == "ball_joint":
            o = j.find("origin")
            assert o is not None
            return np.array([float(v) for v in str(o.get("xyz")).split()])
    raise ValueError("no ball_joint")


class Judge:
    """Held-out KPIs of one calibrated chain + pin on a dataset's placements."""

    def __init__(self, df: pd.DataFrame, train: list[str]) -> None:
        self.df = df
        self.train = train
        self.test = [p for p in placements(df) if p not in train]

    def sub(self, placement: str) -> tuple[np.ndarray, np.ndarray]:
        d = self.df[self.df["placement"] == placement]
        return d[JOINTS].to_numpy(float), d["target_id"].str.endswith("hole_1").to_numpy(int)

    def train_rows(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.df[self.df["placement"].isin(self.train)]
        codes = {t: i for i, t in enumerate(dict.fromkeys(d["target_id"]))}
        return d[JOINTS].to_numpy(float), d["target_id"].map(codes).to_numpy(int)

    def refit(self, chain: Chain) -> np.ndarray:
        q, s = self.train_rows()
        return refit_pin(chain, q, s)

    def __call__(self, chain: Chain, pin: np.ndarray) -> dict[str, Kpi]:
        return self.predictor(lambda q: pin_points(chain, pin, q))

    def predictor(self, predict: Callable[[np.ndarray], np.ndarray]) -> dict[str, Kpi]:
        """KPIs of a pin predictor ``q (N, 7) -> (N, 3)`` on the held-out placements."""
        out = {}
        for p in self.test:
            q, s = self.sub(p)
            out[p] = kpis(predict(q), s)
        return out


def mean_kpi(per: dict[str, Kpi]) -> Kpi:
    return Kpi(
        float(np.mean([k.consistency_mm for k in per.values()])),
        float(np.mean([k.distance_error_mm for k in per.values()])),
    )


Predictor = Callable[[np.ndarray], np.ndarray]


def vtcal_identify(
    df: pd.DataFrame, train: list[str], model: str, work: Path, extra: tuple[str, ...] = ()
) -> tuple[Predictor, float, str]:
    """``vtcal identify`` on the training placements; the pin predictor it delivers.

    A model a URDF can carry is judged by the shipped ``calibrated.urdf`` (to the
    virtual pin), as a URDF consumer uses it. One that it cannot (``elastic``) is
    judged by its own forward map with the identified values of ``parameters.parquet``
    (what a consumer of vtcal's model gets); its rigid part alone is also judged
    (``MODEL urdf``) by the caller through ``calibrated.urdf``.
    """
    from pipeline.cli import cli
    from pipeline.models import get_model

    tag = "+".join(train) + "_" + model
    table = work / f"{tag}.csv"
    cols = ["touchup_id", "target_id", *JOINTS]
    df[df["placement"].isin(train)][cols].to_csv(table, index=False)
    out = work / tag
    args = [
        "identify",
        str(table),
        "--urdf",
        str(nominal_urdf(model)),
        "--out",
        str(out),
        "--flange-link",
        TCP,
        "--no-report",
    ]
    for p in train:
        args += ["--distance", f"{p}/hole_0:{p}/hole_1={DISTANCE_M}"]
    if model != "default":
        args += ["--model", model, "--no-crossval"]
    args += list(extra)
    t0 = time.perf_counter()
    res = CliRunner().invoke(cli, args, prog_name="vtcal", catch_exceptions=False)
    seconds = time.perf_counter() - t0
    if res.exit_code != 0:
        raise RuntimeError(f"vtcal identify {model} failed ({res.exit_code}): {res.output}")
    shipped = ""
    for line in res.output.splitlines():
        if line.startswith("calibrated.urdf from model"):
            shipped = line.split()[-1]
    urdf_chain = load_chain((out / "calibrated.urdf").read_text(), BASE, "virtual_pin")
    if model == "default" or get_model(model).urdf_exact:

        def by_urdf(q: np.ndarray) -> np.ndarray:
            return pin_points(urdf_chain, np.zeros(3), q)

        by_urdf.run_dir = out  # type: ignore[attr-defined]
        return by_urdf, seconds, shipped or model
    from pipeline.use.record import parameter_vector

    em = get_model(model)(load_chain(nominal_urdf(model).read_text(), BASE, TCP))
    xs, pins = parameter_vector(
        pd.read_parquet(out / "parameters.parquet"), model, list(em.param_names)
    )
    x, pin = np.array(xs), np.array(pins)

    def predict(q: np.ndarray) -> np.ndarray:
        return em.pin_and_jacobian(x, q, pin, jac=False)[0]

    predict.urdf_chain = urdf_chain  # type: ignore[attr-defined]
    return predict, seconds, model


def kfold_rms(df: pd.DataFrame, train: list[str], models: list[str]) -> dict[str, float]:
    """k-fold held-out RMS (mm) of each model on the training placements' touch-ups.

    :func:`pipeline.stages.crossval.stage.cross_validate` with 5 folds and no
    leave-one-target-out, on the raw touch-ups with the run's known distances;
    each model on its own nominal URDF (:func:`nominal_urdf`).
    """
    from pipeline.stages.crossval.stage import CrossvalConfig, cross_validate
    from pipeline.stages.identify.stage import IdentifyConfig

    d = df[df["placement"].isin(train)][["touchup_id", "target_id", *JOINTS]].copy()
    codes = {t: i for i, t in enumerate(dict.fromkeys(d["target_id"]))}  # integer target ids
    d["target_id"] = d["target_id"].map(codes)
    dist: list[tuple[int | str, int | str, float]] = [
        (codes[f"{p}/hole_0"], codes[f"{p}/hole_1"], DISTANCE_M) for p in train
    ]
    out = {}
    for m in models:
        res = cross_validate(
            d.reset_index(drop=True),
            nominal_urdf(m).read_text(),
            BASE,
            TCP,
            IdentifyConfig(distances=dist),
            CrossvalConfig(models=[m], loto=False, workers=1),
        )
        out[m] = float(res.summary["models"][m]["kfold_rms_mm"])
    return out


def print_mass_choice(
    dataset: str, train: list[str], kfold: dict[str, float], rows: dict[str, dict[str, Kpi]]
) -> None:
    """The elastic mass-model candidates: k-fold on the training placement vs held out."""
    mukca = mean_kpi(rows["MUKCa"])
    print(
        f"\n{dataset} [{'+'.join(train)}]: mass model of the elastic model "
        f"(MUKCa held out {mukca.consistency_mm:.3f} / {mukca.distance_error_mm:.3f} mm)"
    )
    print(f"  {'model':<18}{'k-fold RMS (train)':>20}{'held-out cons / dist':>24}{'x MUKCa':>9}")
    held = {}
    for m, kf in kfold.items():
        row = rows.get(f"vtcal {m}")
        if row is None:
            continue
        k = mean_kpi(row)
        held[m] = k.consistency_mm
        print(
            f"  {m:<18}{kf:>17.4f} mm{k.consistency_mm:>12.3f} / {k.distance_error_mm:.3f} mm"
            f"{k.consistency_mm / mukca.consistency_mm:>8.2f}"
        )
    elastic = [m for m in held if m.startswith("elastic")]
    if elastic:
        by_kfold = min(elastic, key=lambda m: kfold[m])
        by_held = min(elastic, key=lambda m: held[m])
        print(
            f"  among the elastic candidates k-fold picks {by_kfold}, the held-out placements "
            f"{by_held}" + (" (the same)" if by_kfold == by_held else " (not the same)")
        )
    k_all, h_all = min(held, key=lambda m: kfold[m]), min(held, key=lambda m: held[m])
    print(f"  with full: k-fold picks {k_all}, the held-out placements {h_all}")


def farthest_placement(df: pd.DataFrame, first: str) -> str:
    """The placement whose sockets are farthest from ``first``'s (nominal kinematics)."""
    nominal = load_chain((DATA / "nominal_panda.urdf").read_text(), BASE, TCP)
    pin = ball_pin((DATA / "nominal_panda.urdf").read_text())
    centre = {
        p: pin_points(nominal, pin, g[JOINTS].to_numpy(float)).mean(axis=0)
        for p, g in df.groupby("placement", sort=False)
    }
    return max(centre, key=lambda p: float(np.linalg.norm(centre[p] - centre[first])))


def evaluate(
    dataset: str, train: list[str], models: list[str], work: Path
) -> tuple[dict[str, dict[str, Kpi]], dict[str, str]]:
    """Held-out KPIs of every contender; notes (timings, shipped model)."""
    from pipeline.models import model_names

    df = load_table(dataset)
    judge = Judge(df, train)
    nominal_urdf = (DATA / "nominal_panda.urdf").read_text()
    mukca_urdf = (DATA / f"mukca_calibrated_{dataset}.urdf").read_text()
    nominal = load_chain(nominal_urdf, BASE, TCP)
    mukca = load_chain(mukca_urdf, BASE, TCP)
    rows: dict[str, dict[str, Kpi]] = {
        "nominal": judge(nominal, ball_pin(nominal_urdf)),
        "nominal+pin": judge(nominal, judge.refit(nominal)),
        "MUKCa": judge(mukca, ball_pin(mukca_urdf)),
        "MUKCa+pin": judge(mukca, judge.refit(mukca)),
    }
    notes: dict[str, str] = {}
    names = [m for m in models if m != "all"]
    if "all" in models:
        names = ["default", *BASE_MODELS, *[m for m in model_names() if m not in BASE_MODELS]]
    for m in names:
        predict, seconds, shipped = vtcal_identify(df, train, m, work)
        label = f"vtcal {m}" + (f" (-> {shipped})" if m == "default" else "")
        rows[label] = judge.predictor(predict)
        notes[label] = f"{seconds:.1f} s"
        rigid = getattr(predict, "urdf_chain", None)
        if rigid is not None:  # a model a URDF cannot carry: its calibrated.urdf alone too
            rows[f"vtcal {m} (urdf only)"] = judge(rigid, np.zeros(3))
        if m == "default":  # the same run through vtcal predict: the model it predicts with
            run_dir = predict.run_dir  # type: ignore[attr-defined]
            used = json.loads((run_dir / "calibration.json").read_text())["model"]
            t0 = time.perf_counter()
            rows[f"vtcal predict (-> {used})"] = judge.predictor(
                lambda q, d=run_dir: vtcal_predict(d, q, work)
            )
            notes[f"vtcal predict (-> {used})"] = f"{time.perf_counter() - t0:.1f} s"
    return rows, notes


def vtcal_predict(run_dir: Path, q: np.ndarray, work: Path) -> np.ndarray:
    """``vtcal predict RUN_DIR --joints J.csv --out P.csv`` (the click command, in process):
    the pin positions (base frame, m) the run's calibration.json model predicts at ``q``."""
    from pipeline.cli import cli

    joints, out = work / "predict_joints.csv", work / "predicted.csv"
    pd.DataFrame(q, columns=JOINTS).to_csv(joints, index=False)
    args = ["predict", str(run_dir), "--joints", str(joints), "--out", str(out)]
    res = CliRunner().invoke(cli, args, prog_name="vtcal", catch_exceptions=False)
    if res.exit_code != 0:
        raise RuntimeError(f"vtcal predict failed ({res.exit_code}): {res.output}")
    return pd.read_csv(out)[["pin_x_m", "pin_y_m", "pin_z_m"]].to_numpy(float)


def floors(dataset: str, models: tuple[str, ...], work: Path) -> None:
    """``--floors``: each held-out placement judged after training on every other
    placement, and after fitting it on itself (see the module docstring)."""
    df = load_table(dataset)
    held = [p for p in placements(df) if p != TRAIN[dataset]]
    mukca_urdf = (DATA / f"mukca_calibrated_{dataset}.urdf").read_text()
    mukca = mean_kpi(
        Judge(df, [TRAIN[dataset]])(load_chain(mukca_urdf, BASE, TCP), ball_pin(mukca_urdf))
    )
    goal = 0.8 * mukca.consistency_mm
    print(
        f"\n{dataset}: what more data buys (held out: the {len(held)} placements of the "
        f"{TRAIN[dataset]} split; goal {goal:.3f} mm = 80 % of MUKCa's {mukca.consistency_mm:.3f})"
    )
    print("consistency / distance error (mm), trained on every other placement | fitted on itself")
    for model in models:
        others, itself = {}, {}
        judge = Judge(df, [])
        for p in held:
            q, s = judge.sub(p)
            rest = [x for x in placements(df) if x != p]
            predict, _, _ = vtcal_identify(df, rest, model, work)
            others[p] = kpis(predict(q), s)
            predict, _, _ = vtcal_identify(df, [p], model, work)
            itself[p] = kpis(predict(q), s)
        mo, mi = mean_kpi(others), mean_kpi(itself)
        print(
            f"  {model:<8} mean {mo.consistency_mm:.3f} / {mo.distance_error_mm:.3f} | "
            f"{mi.consistency_mm:.3f} / {mi.distance_error_mm:.3f}   "
            + "  ".join(
                f"{p} {others[p].consistency_mm:.3f}|{itself[p].consistency_mm:.3f}" for p in held
            )
        )


def print_table(
    dataset: str, train: list[str], rows: dict[str, dict[str, Kpi]], notes: dict[str, str]
) -> None:
    test = list(next(iter(rows.values())))
    print(f"\n{dataset}: trained on {' + '.join(train)}; held out: {len(test)} placements")
    print("consistency / distance error, mm, per held-out placement and their mean")
    w = max(len(r) for r in rows) + 2
    head = "".ljust(w) + "".join(p[:13].rjust(14) for p in test) + "mean".rjust(14) + "  time"
    print(head)
    for r, per in rows.items():
        cells = "".join(
            f"{per[p].consistency_mm:.3f}/{per[p].distance_error_mm:.3f}".rjust(14) for p in test
        )
        m = mean_kpi(per)
        mean = f"{m.consistency_mm:.3f}/{m.distance_error_mm:.3f}".rjust(14)
        print(r.ljust(w) + cells + mean + "  " + notes.get(r, ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS))
    ap.add_argument(
        "--models",
        nargs="+",
        default=["all"],
        help="vtcal models to run: 'all' (default, full, mdh, poe, offsets and every "
        "registered model) or names ('default' = no --model)",
    )
    ap.add_argument("--no-two", action="store_true", help="skip the two-placement training")
    ap.add_argument(
        "--no-mass",
        action="store_true",
        help="skip the k-fold figures of the elastic mass-model candidates (and full)",
    )
    ap.add_argument(
        "--floors",
        action="store_true",
        help="also train on every placement but one and fit each placement on itself "
        "(full, elastic): what more data buys",
    )
    args = ap.parse_args()
    t_all = time.perf_counter()
    summary: list[tuple[str, str, dict[str, Kpi]]] = []
    with tempfile.TemporaryDirectory(prefix="bench_real_") as tmp:
        work = Path(tmp)
        for ds in args.datasets:
            splits = [[TRAIN[ds]]]
            if not args.no_two:
                splits.append([TRAIN[ds], farthest_placement(load_table(ds), TRAIN[ds])])
            for train in splits:
                t0 = time.perf_counter()
                rows, notes = evaluate(ds, train, args.models, work)
                print_table(ds, train, rows, notes)
                if not args.no_mass:
                    cands = [m for m in MASS_CANDIDATES if f"vtcal {m}" in rows]
                    kf = kfold_rms(load_table(ds), train, cands)
                    print_mass_choice(ds, train, kf, rows)
                print(f"({time.perf_counter() - t0:.1f} s)")
                summary.append((ds, "+".join(train), {r: mean_kpi(v) for r, v in rows.items()}))
        if args.floors:
            for ds in args.datasets:
                floors(ds, ("full", "elastic"), work)
    print("\nheld-out means, consistency / distance error (mm)")
    for ds, train, means in summary:
        print(f"{ds} [{train}]")
        for r, m in means.items():
            print(f"  {r:<34} {m.consistency_mm:.3f} / {m.distance_error_mm:.3f}")
    print(f"total {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
