"""The error budget of a touch-up: each source predicted and measured on its own.

For recordings whose truth file carries every image's true joint angles, the true
camera and the targets' geometry (the independent generator's format: the
conformance sample and ``../shared/foreign``), the touch-ups vtcal extracts are
judged source by source, in micrometres of the corrected pin (flange frame),
through vtcal's own image Jacobian ``d_F = -J^-1 e``:

- **predicted** from the recording alone (:mod:`pipeline.stages.touchups.noise`):
  the repeated captures' detection noise (N1)-(N2), the pose component the loop's
  small steps show (N3), and their sum (N4);
- **measured** against the truth, per touch-up (its converged captures):

  * detection noise: each capture's ``(u, v, 1/s)`` less the true ellipse's
    (the circle's exact projection with the true camera and lens), the scatter
    within a touch-up over ``sqrt(n)``;
  * pose component: the scatter of the touch-ups' mean detection errors beyond
    that (same at every capture of a pose, new at the next);
  * constant detection bias: their mean (the pin absorbs it; no residual shows it);
  * joint encoder and interpolation at the image stamp: the pin moved by the
    joint vector vtcal took against the true one (true robot);
  * perspective: the ellipse's centre and long axis against the projected
    centre and the untilted size, left after vtcal's tilt correction;
  * lens distortion around the designated point: the true ellipse with and
    without the lens;
  * the correction and convergence chain: what the total leaves after the above;
  * the total: the corrected pin against the true target centre.

Along = along the camera's view, across = the two axes across it; "mean" is the
constant part, "sd" the part that changes from touch-up to touch-up (the part a
covariance must hold). ``--write`` puts the table into docs/error-budget.md.

Usage::

    python benchmarks/bench_error_budget.py [REC.mcap ...] [--simulate SEED ...] [--write]

``--simulate SEED`` adds our own simulator's standard LR Mate-like cell
(``datasets/scenarios/standard.toml``, that seed, 36 touch-ups, three captures each),
simulated into a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.kinematics.chain import fk, load_chain
from pipeline.sim.target_geometry import fit_ellipse
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording
from pipeline.stages.touchups.stage import TouchupConfig, extract_touchups

SHARED = Path(__file__).resolve().parents[2] / "shared"
DEFAULT = [
    SHARED / "samples" / "conformance_lrmate_small.mcap",
    SHARED / "foreign" / "lrmate51_day0.mcap",
    SHARED / "foreign" / "lrmate51_day7.mcap",
]
SCENARIO = Path(__file__).resolve().parents[1] / "datasets" / "scenarios" / "standard.toml"
DOC = Path(__file__).resolve().parents[1] / "docs" / "error-budget.md"
_PHI = np.linspace(0.0, 2.0 * np.pi, 1440, endpoint=False)


def _true_image(truth: dict[str, Any], chain: Any, q: np.ndarray, target: dict[str, Any]):
    """True ellipse with and without the lens, projected centre, untilted size, depth."""
    cam = truth["camera"]
    T_cb = np.linalg.inv(fk(chain, q) @ np.array(cam["T_flange_camera"]))
    c, n = np.array(target["centre"]), np.array(target["normal"], dtype=float)
    n /= np.linalg.norm(n)
    a = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    R = target["diameter_m"] / 2
    P = c + R * (np.cos(_PHI)[:, None] * a + np.sin(_PHI)[:, None] * b)
    Pc = P @ T_cb[:3, :3].T + T_cb[:3, 3]
    cc = T_cb[:3, :3] @ c + T_cb[:3, 3]

    def project(X: np.ndarray, lens: bool) -> np.ndarray:
        x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
        r2 = x * x + y * y
        g = 1 + cam["k1"] * r2 + cam["k2"] * r2 * r2 if lens else 1.0
        return np.stack([cam["fx"] * x * g + cam["cx"], cam["fy"] * y * g + cam["cy"]], axis=-1)

    centre = project(cc, True)
    return (
        np.array(fit_ellipse(project(Pc, True))[:3]),  # u, v, long axis
        np.array(fit_ellipse(project(Pc, False))[:3]),
        np.array([centre[0], centre[1], cam["fx"] * 2 * R / cc[2]]),
    )


def _m(e: np.ndarray) -> np.ndarray:
    """``(u, v, s)`` rows -> ``(u, v, 1/s)``."""
    return np.stack([e[..., 0], e[..., 1], 1.0 / e[..., 2]], axis=-1)


def evaluate(path: Path) -> dict[str, Any]:
    truth = json.loads(Path(str(path) + ".truth.json").read_text())
    frames, dets, info = ingest_recording(path, IngestConfig(), DetectConfig())
    tu = extract_touchups(frames, dets, info, TouchupConfig())
    noise = tu.attrs["capture_noise"]
    J = np.array(tu.attrs["image_jacobian"])
    Ji = np.linalg.inv(J)
    chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    p_pin = np.array(truth["p_vt_flange"])
    T_fc = np.array(truth["camera"]["T_flange_camera"])
    view = T_fc[:3, 2]
    by_last = {t["image_indices"][-1]: t for t in truth["touchups"]}
    images = truth["images"]
    targets = {t["id"]: t for t in truth["targets"]}
    det = dets.set_index("frame_index")
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("within", "mean", "enc", "persp", "lens")}
    total, n_caps = [], []
    for _, r in tu[tu["converged"]].iterrows():
        t = by_last.get(int(r.last_frame))
        if t is None:
            continue
        caps = [int(k) for k in r.converged_frame_indices if int(k) in det.index]
        if len(caps) == 0:
            continue
        # the centre at this touch-up (a knocked target's history), the plate's normal
        tgt = {**targets[t["target"]], "centre": t["target_centre"]}
        trues = [_true_image(truth, chain, np.array(images[k]["q_true"]), tgt) for k in caps]
        err = np.array(
            [
                _m(det.loc[k, ["u", "v", "s"]].to_numpy(float)) - _m(e)
                for k, (e, _, _) in zip(caps, trues, strict=True)
            ]
        )
        if len(caps) > 1:
            rows["within"].append(
                (err - err.mean(axis=0)) @ -Ji.T * np.sqrt(len(caps) / (len(caps) - 1))
            )
        rows["mean"].append(err.mean(axis=0) @ -Ji.T)
        n_caps.append(len(caps))
        ell, flat, proj = trues[-1]
        bias = np.array([r.bias_u_px, r.bias_v_px, r.bias_s_px])
        # vtcal's corrected ellipse (u + bias_u, v + bias_v, s - bias_s) against the projected
        # centre and the untilted size, each without the lens (the lens is its own row)
        corr = np.array([flat[0] + bias[0], flat[1] + bias[1], flat[2] - bias[2]])
        proj_flat = np.array([proj[0], proj[1], proj[2]]) - (ell - flat) * np.array([1, 1, 0])
        rows["persp"].append((_m(corr) - _m(proj_flat)) @ -Ji.T)
        rows["lens"].append((_m(ell) - _m(flat)) @ -Ji.T)
        q = r[info.joint_names].to_numpy(float)
        Tm, Tt = fk(chain, q), fk(chain, np.array(t["q"]))
        rows["enc"].append(
            Tt[:3, :3].T @ ((Tm[:3, :3] - Tt[:3, :3]) @ p_pin + Tm[:3, 3] - Tt[:3, 3])
        )
        d = r[["dx_flange", "dy_flange", "dz_flange"]].to_numpy(float)
        e_total = Tm[:3, :3] @ (p_pin + d) + Tm[:3, 3] - np.array(t["target_centre"])
        total.append(Tm[:3, :3].T @ e_total)
    W = np.concatenate(rows["within"]) if rows["within"] else np.zeros((0, 3))
    M = np.array(rows["mean"])
    n_eff = len(n_caps) / float(np.sum(1.0 / np.array(n_caps)))
    cov_within = (
        W.T @ W / max(len(W) - len(rows["within"]), 1) / n_eff if len(W) else np.zeros((3, 3))
    )
    cov_between = np.cov(M.T)
    cov_pose = cov_between - cov_within
    E = np.array(total)
    explained = M + np.array(rows["enc"]) + np.array(rows["persp"]) + np.array(rows["lens"])
    chain_rest = E - explained

    def split(cov: np.ndarray) -> tuple[float, float]:
        along = float(view @ cov @ view)
        return 1e6 * np.sqrt(max(along, 0.0)), 1e6 * np.sqrt(max(np.trace(cov) - along, 0.0))

    def stats(X: np.ndarray) -> dict[str, float]:
        X = np.asarray(X, dtype=float)
        mean = X.mean(axis=0)
        sd_a, sd_x = split(np.cov(X.T) if len(X) > 1 else np.zeros((3, 3)))
        return {
            "mean_along": 1e6 * float(mean @ view),
            "mean_across": 1e6 * float(np.linalg.norm(mean - (mean @ view) * view)),
            "sd_along": sd_a,
            "sd_across": sd_x,
        }

    pa, px = (
        split(np.array(noise["cov_flange_m2"]) / noise["n_eff"])
        if np.isfinite(noise["n_eff"])
        else (float("nan"),) * 2
    )
    qa, qx = split(np.array(noise["cov_pose_flange_m2"]))
    wa, wx = split(cov_within)
    ba, bx = split(cov_pose)
    return {
        "name": path.stem,
        "n": len(E),
        "predicted": {"capture": (pa, px), "pose": (qa, qx)},
        "measured_capture": (wa, wx),
        "measured_pose": (ba, bx),
        "detection": stats(M),
        "encoder": stats(rows["enc"]),
        "perspective": stats(rows["persp"]),
        "lens": stats(rows["lens"]),
        "chain": stats(chain_rest),
        "total": stats(E),
        "rms_touchup_um": noise["rms_touchup_um"],
        "rms_capture_um": noise["rms_capture_um"],
    }


def table(results: list[dict[str, Any]]) -> str:
    head = (
        "| source (um of pin, along / across the view) | "
        + " | ".join(f"{r['name']} ({r['n']})" for r in results)
        + " |"
    )
    out = [head, "|---|" + "---|" * len(results)]

    def cell(pair: tuple[float, float]) -> str:
        return f"{pair[0]:.1f} / {pair[1]:.1f}"

    def row(label: str, f: Any) -> None:
        out.append(f"| {label} | " + " | ".join(f(r) for r in results) + " |")

    row(
        "detection noise per capture at one pose, predicted (N1-N2, n-averaged)",
        lambda r: cell(r["predicted"]["capture"]),
    )
    row("the same, measured against the true ellipses", lambda r: cell(r["measured_capture"]))
    row("pose component of detection, predicted (N3)", lambda r: cell(r["predicted"]["pose"]))
    row(
        "the same, measured (scatter of per-pose means beyond the captures')",
        lambda r: cell(r["measured_pose"]),
    )
    row(
        "constant detection bias (mean; the pin absorbs it)",
        lambda r: f"{r['detection']['mean_along']:+.1f} / {r['detection']['mean_across']:.1f}",
    )
    for key, label in (
        ("encoder", "joint encoder + interpolation at the stamp, sd"),
        ("perspective", "perspective offset left after the tilt correction, sd"),
        ("lens", "lens distortion around the designated point, sd"),
        ("chain", "correction and convergence chain (the rest), sd"),
    ):
        row(label, lambda r, k=key: f"{r[k]['sd_along']:.1f} / {r[k]['sd_across']:.1f}")
    for key, label in (
        ("perspective", "perspective, mean"),
        ("lens", "lens distortion, mean"),
        ("chain", "correction chain, mean"),
    ):
        row(label, lambda r, k=key: f"{r[k]['mean_along']:+.1f} / {r[k]['mean_across']:.1f}")
    row(
        "**total, sd** (the corrected pin against the true centre)",
        lambda r: f"**{r['total']['sd_along']:.1f} / {r['total']['sd_across']:.1f}**",
    )
    row(
        "**total, mean**",
        lambda r: f"**{r['total']['mean_along']:+.1f} / {r['total']['mean_across']:.1f}**",
    )
    row(
        "noise model per touch-up, RMS: captures alone -> captures + pose (N4)",
        lambda r: f"{r['rms_capture_um']:.1f} -> {r['rms_touchup_um']:.1f}",
    )
    row(
        "observed sd RMS / (N4)",
        lambda r: (
            f"{np.hypot(r['total']['sd_along'], r['total']['sd_across']) / r['rms_touchup_um']:.2f}"
        ),
    )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recordings", nargs="*", type=Path)
    ap.add_argument(
        "--write", action="store_true", help="write the table into docs/error-budget.md"
    )
    ap.add_argument(
        "--simulate",
        type=int,
        nargs="*",
        default=[],
        metavar="SEED",
        help="add our simulator's standard cell at these seeds",
    )
    ap.add_argument(
        "--also",
        type=Path,
        nargs="*",
        default=[],
        metavar="MCAP",
        help="recordings added after the defaults, e.g. bench_render.py's Mitsuba renders "
        "(its cache: /work/renders/lrmate_linear_s201.mcap ...)",
    )
    a = ap.parse_args()
    recordings = list(a.recordings or DEFAULT) + list(a.also)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in a.simulate:
            from pipeline.sim.scenario import load_scenario
            from pipeline.sim.simulator import write_recording

            rec = Path(tmp) / f"our_simulator_standard_s{seed}.mcap"
            write_recording(load_scenario(SCENARIO), seed, rec)
            recordings.append(rec)
        results = [evaluate(p) for p in recordings]
    text = table(results)
    print(text)
    if a.write:
        doc = DOC.read_text()
        new = re.sub(
            r"(<!-- budget -->\n).*?(<!-- /budget -->)",
            lambda m: m.group(1) + text.rstrip("\n") + "\n" + m.group(2),
            doc,
            flags=re.S,
        )
        DOC.write_text(new)
        print(f"written: {DOC}")


if __name__ == "__main__":
    main()
