"""Touch-up extraction accuracy against ground truth (prints figures measured in one run).

For each recording (default: the conformance sample; more with arguments,
e.g. ``vtcal simulate`` outputs with their ``.truth.json``):

- touch-ups found / assigned to the right target / converged as the truth says;
- the converged virtual-pin position under the TRUE kinematics
  (``true_urdf_with_pin``), ``T_base_flange_true(q) (p_pin + d_F)``, against
  the true target centre: RMS error with and without the residual correction
  ``d_F``, split into the part along the camera's optical axis (along-view)
  and the lateral part;
- on recordings whose truth has the renderer's exact ellipses (``vtcal
  simulate``): the same extraction from those ellipses instead of the
  detections (what the touch-up stage and the truth's pin definition leave),
  the detector's mean size error over all images, and the fit of the
  along-view error per touch-up against the size error of its converged
  captures (slope and the constant left over).

Usage::

    python benchmarks/bench_touchup.py [REC.mcap ...]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.kinematics.chain import fk, load_chain
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording
from pipeline.stages.touchups.stage import TouchupConfig, extract_touchups

SAMPLE = Path("/work/shared/samples/conformance_lrmate_small.mcap")


def evaluate(path: Path) -> dict[str, float]:
    truth = json.loads(Path(str(path) + ".truth.json").read_text())
    t0 = time.perf_counter()
    frames, dets, info = ingest_recording(path, IngestConfig(), DetectConfig())
    tu = extract_touchups(frames, dets, info, TouchupConfig())
    dt = time.perf_counter() - t0
    ttu = truth["touchups"]
    # match by the last frame of the touch-up
    by_last = {t["image_indices"][-1]: t for t in ttu}
    found = sum(1 for lf in tu["last_frame"] if int(lf) in by_last)
    right_target = sum(
        1
        for _, r in tu.iterrows()
        if int(r.last_frame) in by_last and by_last[int(r.last_frame)]["label"] == int(r.target_id)
    )
    right_conv = sum(
        1
        for _, r in tu.iterrows()
        if int(r.last_frame) in by_last
        and bool(by_last[int(r.last_frame)]["converged"]) == bool(r.converged)
        and bool(by_last[int(r.last_frame)].get("lost", False)) == bool(r.lost)
    )
    chain = load_chain(truth["true_urdf"], truth["base_link"], truth["flange_link"])
    p_pin = np.array(truth["p_vt_flange"])
    T_fc = np.array(truth["camera"]["T_flange_camera"])
    conv = tu[tu["converged"]]
    q = conv[info.joint_names].to_numpy(float)
    T = fk(chain, q)
    d = conv[["dx_flange", "dy_flange", "dz_flange"]].to_numpy(float)
    c_true = np.array([by_last[int(lf)]["target_centre"] for lf in conv["last_frame"]])
    s_det = dets.set_index("frame_index")["s"]
    p_raw = T[:, :3, :3] @ p_pin + T[:, :3, 3]
    p_cor = np.einsum("nij,nj->ni", T[:, :3, :3], p_pin + d) + T[:, :3, 3]
    z_cam = T[:, :3, :3] @ T_fc[:3, 2]

    def split(p: np.ndarray) -> tuple[float, float, float]:
        e = p - c_true
        along = np.einsum("ni,ni->n", e, z_cam)
        lat = e - along[:, None] * z_cam
        return (
            float(np.sqrt(np.mean(np.sum(e**2, 1)))) * 1e3,
            float(np.sqrt(np.mean(along**2))) * 1e3,
            float(np.sqrt(np.mean(np.sum(lat**2, 1)))) * 1e3,
        )

    raw = split(p_raw)
    cor = split(p_cor)
    e_al = np.einsum("ni,ni->n", p_cor - c_true, z_cam)
    al_c = float(np.std(e_al)) * 1e3
    print(
        f"{path.name}: {len(tu)} touch-ups found (truth {len(ttu)}), matched {found}, "
        f"right target {right_target}, right converged/lost {right_conv}; "
        f"ingest+extraction {dt:.2f} s"
    )
    print(f"  converged: {len(conv)}; pin error RMS (true kinematics), mm:")
    print(
        f"    without correction: total {raw[0]:.4f}  along-view {raw[1]:.4f}  lateral {raw[2]:.4f}"
    )
    print(
        f"    with correction:    total {cor[0]:.4f}  along-view {cor[1]:.4f}  lateral {cor[2]:.4f}"
    )
    print(f"    ratio corrected/uncorrected: {cor[0] / raw[0]:.3f}")
    print(
        f"    along-view mean {np.mean(e_al) * 1e3:+.4f} mm (a constant the identified pin absorbs), "
        f"scatter {al_c:.4f} mm"
    )
    if all("true_ellipse" in im for im in truth["images"]):
        # the same extraction from the renderer's exact ellipses: what is left is
        # the touch-up stage and the truth's pin definition, detection removed
        te = {int(im["index"]): im["true_ellipse"] for im in truth["images"]}
        exact = dets.copy()
        ell = np.array([te[int(i)] for i in exact["frame_index"]])
        exact["u"], exact["v"], exact["s"], exact["s_minor"], exact["angle"] = ell.T
        tx = extract_touchups(frames, exact, info, TouchupConfig())
        tx = tx[tx["converged"]].set_index("touchup_id").loc[conv["touchup_id"]]
        d_x = tx[["dx_flange", "dy_flange", "dz_flange"]].to_numpy(float)
        p_x = np.einsum("nij,nj->ni", T[:, :3, :3], p_pin + d_x) + T[:, :3, 3]
        e_x = np.einsum("ni,ni->n", p_x - c_true, z_cam)
        ds = np.array(
            [
                np.mean([float(s_det[i]) - te[i][2] for i in map(int, fl)])
                for fl in conv["converged_frame_indices"]
            ]
        )
        A = np.stack([ds, np.ones_like(ds)], axis=1)
        coef, *_ = np.linalg.lstsq(A, e_al, rcond=None)
        ok = dets["found"].to_numpy(bool)
        ds_all = dets["s"].to_numpy(float)[ok] - ell[ok, 2]
        print(
            f"    from the exact ellipses: along-view mean {np.mean(e_x) * 1e3:+.4f} mm, "
            f"scatter {np.std(e_x) * 1e3:.4f} mm"
        )
        print(
            f"    detector size error (all {ok.sum()} images) {np.mean(ds_all):+.5f} px "
            f"(SE {np.std(ds_all) / np.sqrt(ok.sum()):.5f}); along-view = "
            f"{coef[0] * 1e3:.3f} mm/px * ds {coef[1] * 1e3:+.4f} mm "
            f"(rest {np.std(e_al - A @ coef) * 1e3:.4f} mm)"
        )
    return {"raw": raw[0], "cor": cor[0], "along": cor[1], "lat": cor[2], "scatter": al_c}


def main() -> None:
    paths = [Path(p) for p in sys.argv[1:]] or [SAMPLE]
    res = [evaluate(p) for p in paths]
    if len(res) > 1:
        cor = np.sqrt(np.mean([r["cor"] ** 2 for r in res]))
        raw = np.sqrt(np.mean([r["raw"] ** 2 for r in res]))
        al = np.sqrt(np.mean([r["along"] ** 2 for r in res]))
        lat = np.sqrt(np.mean([r["lat"] ** 2 for r in res]))
        print(
            f"all recordings: corrected RMS {cor:.4f} mm (along-view {al:.4f}, lateral {lat:.4f}), "
            f"uncorrected {raw:.4f} mm"
        )


if __name__ == "__main__":
    main()
