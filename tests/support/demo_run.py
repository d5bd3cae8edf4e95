"""A small synthetic run folder, for tests and demos of the report and the Rerun recording.

:func:`make_demo_run` writes every artefact a finished run leaves (see
``spec/outputs.md``) for a built-in arm, with known geometry: a
"true" robot (the nominal URDF with small origin errors), a virtual pin and a
few targets; touch-ups are joint vectors that put the true pin on a target
(solved by damped Gauss-Newton from varied starts), some of them rejected with
a reason. Optionally a tiny MCAP recording with one rendered image per capture
is written too, so the image paths (thumbnails, Rerun images) can be exercised
without a real recording. Nothing here is used by a real run.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.artefacts import SCHEMA_DIR, load_schema, write_artefact
from pipeline.kinematics.chain import Chain, fk, jacobian, load_chain
from pipeline.kinematics.se3 import matrix_from_rpy
from pipeline.kinematics.urdf_write import write_calibrated_urdf
from pipeline.robots import builtin_urdf

W, H = 320, 256
IMAGE_TOPIC = "/camera/image_raw"

_IMAGE_MSGDEF = """std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""


def _solve_touch(chain: Chain, q0: np.ndarray, target: np.ndarray, p_pin: np.ndarray) -> np.ndarray:
    """Joint vector near ``q0`` with ``T_base_flange(q) p_pin = target`` (damped Gauss-Newton)."""
    q = q0.copy()
    for _ in range(30):
        T = fk(chain, q)
        p = T[:3, :3] @ p_pin + T[:3, 3]
        e = target - p
        if np.linalg.norm(e) < 1e-12:
            break
        J = jacobian(chain, q, p_pin)[:3]
        q = q + J.T @ np.linalg.solve(J @ J.T + 1e-9 * np.eye(3), e)
    return q


_DEFAULTS: dict[str, Any] = {
    "float64": float("nan"),
    "int64": 0,
    "int32": 0,
    "bool": False,
    "string": "",
    "binary": b"",
}


def _write(path: Path, df: pd.DataFrame, schema: str) -> None:
    """Through the declared schema when there is one, else as plain Parquet.

    Declared columns the demo does not know (a schema grew) get a neutral value
    (NaN, 0, False, '' or an empty list), so the demo keeps up with the schemas.
    """
    if (SCHEMA_DIR / f"{schema}.json").exists():
        df = df.copy()
        for col in load_schema(schema).columns:
            if col.name not in df.columns:
                if col.type.startswith("list<"):
                    df[col.name] = [[] for _ in range(len(df))]
                else:
                    df[col.name] = _DEFAULTS[col.type]
        write_artefact(path, df, schema, stage="demo")
    else:
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path)


def _render(u: float, v: float, s: float, rng: np.random.Generator) -> np.ndarray:
    img = np.full((H, W), 200, np.uint8)
    cv2.ellipse(
        img,
        (round(u * 16), round(v * 16)),
        (round(s / 2 * 16), round(s / 2 * 0.9 * 16)),
        20.0,
        0,
        360,
        40,
        -1,
        cv2.LINE_AA,
        4,
    )
    noise = rng.normal(0, 3, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def make_demo_run(
    run_dir: Path,
    *,
    seed: int = 0,
    n_targets: int = 3,
    poses_per_target: int = 4,
    with_recording: bool = True,
    known_distance: bool = False,
) -> Path:
    """Write a complete synthetic run folder into ``run_dir``; return it.

    Parameters
    ----------
    run_dir : folder to create
    seed : random seed (the folder is a pure function of the arguments)
    n_targets, poses_per_target : size of the run
    with_recording : also write ``recording.mcap`` (one image per capture) and
        point ``recording.json`` at it
    known_distance : put a ``known_distances`` key in the metadata (scale identified)
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    urdf = builtin_urdf("lrmate")
    nominal = load_chain(urdf, "base_link", "flange")
    names = nominal.joint_names
    # the "true" robot: small origin errors on every actuated joint
    origins = {}
    for j in nominal.actuated:
        T = j.T_parent_joint.copy()
        T[:3, 3] += rng.normal(0, 0.0008, 3)
        T[:3, :3] = T[:3, :3] @ matrix_from_rpy(rng.normal(0, 0.0008, 3))
        origins[j.name] = T
    true = nominal.with_origins(origins)
    p_pin = np.array([0.0, 0.0, 0.18])
    targets = np.array([[0.55, -0.15 + 0.15 * k, 0.10 + 0.03 * k] for k in range(n_targets)])
    d0 = (W - 1) / 2, (H - 1) / 2, 60.0

    rows = []
    frames = []
    dets = []
    images: list[tuple[int, np.ndarray]] = []
    frame_touchup: list[int] = []
    t0 = 1_790_000_000_000_000_000
    frame = 0
    tid = 0
    for k, tgt in enumerate(targets):
        for _ in range(poses_per_target):
            q0 = np.array([np.arctan2(tgt[1], tgt[0]), 0.3, -0.2, 0.0, -1.2, 0.0])
            q0 = q0 + rng.normal(0, 0.25, 6) * np.array([0.2, 0.5, 0.5, 1.5, 0.5, 1.5])
            q = _solve_touch(true, q0, tgt, p_pin)
            n_iter = int(rng.integers(3, 6))
            converged = not (tid % 7 == 5)
            e = np.array([rng.normal(0, 12), rng.normal(0, 12), rng.normal(0, 8)])
            for it in range(n_iter):
                stamp = t0 + frame * 200_000_000
                frames.append(
                    {"frame_index": frame, "stamp_ns": stamp, "log_time_ns": stamp,
                     "max_joint_speed": 0.0, "joint_gap_ns": 10_000_000,
                     "nearest_joint_dt_ns": 1_000_000, "moving": False, "joint_gap": False,
                     "extrapolated": False, **dict(zip(names, q, strict=True))}
                )  # fmt: skip
                frame_touchup.append(tid)
                if it == n_iter - 1 and converged:
                    e = rng.normal(0, 0.15, 3)
                u, v, s = d0[0] + e[0], d0[1] + e[1], d0[2] + e[2]
                dets.append(
                    {"frame_index": frame, "found": True, "u": u, "v": v, "s": s,
                     "s_minor": 0.9 * s, "angle": np.deg2rad(20.0), "s_inv": 1.0 / s,
                     "residual_px": 0.05, "completeness": 1.0, "border_contact": False,
                     "n_blobs": 1, "ambiguity": 0.0, "ambiguous": False, "contrast": 160.0,
                     "edge_sigma_px": 0.8, "n_edge_points": 200, "quality_ok": True,
                     "reason": ""}
                )  # fmt: skip
                images.append((frame, _render(u, v, s, rng)))
                e = e * 0.25
                frame += 1
            fr = list(range(frame - n_iter, frame))
            hist = np.array(
                [[d["u"] - d0[0], d["v"] - d0[1], d["s"] - d0[2]] for d in dets[-n_iter:]]
            )
            rows.append(
                {"touchup_id": tid, "target_id": k, "dx_flange": 0.0, "dy_flange": 0.0,
                 "dz_flange": 0.0, "weight": 1.0, "converged": converged, "stamp_ns": stamp,
                 "lost": False, "moving": False, "first_frame": fr[0], "last_frame": fr[-1],
                 "loop_start_frame": fr[0], "n_probe_frames": 0, "frame_indices": fr,
                 "converged_frame_indices": fr[-1:], "n_captures": n_iter,
                 "n_converged_captures": 1, "n_iterations": n_iter - 1,
                 "e_u_history": hist[:, 0], "e_v_history": hist[:, 1],
                 "e_s_history": hist[:, 2], "jacobian_source": "global",
                 "u": d0[0] + hist[-1, 0], "v": d0[1] + hist[-1, 1], "s": d0[2] + hist[-1, 2],
                 "e_u": hist[-1, 0], "e_v": hist[-1, 1], "e_s_px": hist[-1, 2],
                 "e_sinv": 1 / (d0[2] + hist[-1, 2]) - 1 / d0[2], "fit_residual_px": 0.05,
                 "border_contact": False, "ambiguous": False,
                 **dict(zip(names, q, strict=True))}
            )  # fmt: skip
            tid += 1
    touch = pd.DataFrame(rows)
    _write(run_dir / "touchups.parquet", touch, "touchups")
    inl = touch[["touchup_id", "target_id", "dx_flange", "dy_flange", "dz_flange", "weight",
                 "converged", "stamp_ns", *names]].copy()  # fmt: skip
    inl.insert(2, "source_target_id", inl["target_id"])
    inl["inlier"] = inl["converged"]
    inl["reason"] = np.where(inl["converged"], "", "not converged")
    inl.loc[inl.index[1], "inlier"] = False
    inl.loc[inl.index[1], "reason"] = "captured while moving"
    _write(run_dir / "inliers.parquet", inl, "inliers")
    _write(run_dir / "frames.parquet", pd.DataFrame(frames), "frames")
    _write(run_dir / "detections.parquet", pd.DataFrame(dets), "detections")

    # identification result: the true robot, pin and targets (tiny noise)
    q_all = touch[names].to_numpy(float)
    tg = targets[touch["target_id"].to_numpy()]
    res = []
    for ch in (true,):
        T = fk(ch, q_all)
        p = np.einsum("nij,j->ni", T[:, :3, :3], p_pin) + T[:, :3, 3]
        r = p - tg + rng.normal(0, 2e-5, p.shape)
        for i, t in enumerate(touch["touchup_id"]):
            used = bool(inl["inlier"].iloc[i])
            res.append(
                {"model": "full", "touchup_id": int(t),
                 "target_id": int(touch["target_id"].iloc[i]),
                 "target_label": str(touch["target_id"].iloc[i]), "used": used,
                 "reason": "" if used else str(inl["reason"].iloc[i]), "weight": 1.0,
                 "rx": r[i, 0], "ry": r[i, 1], "rz": r[i, 2],
                 "norm": float(np.linalg.norm(r[i])), "px": p[i, 0], "py": p[i, 1],
                 "pz": p[i, 2]}
            )  # fmt: skip
    _write(run_dir / "residuals.parquet", pd.DataFrame(res), "residuals")
    tgt_df = pd.DataFrame(
        {"model": "full", "target_id": np.arange(n_targets),
         "target_label": [str(k) for k in range(n_targets)], "x": targets[:, 0],
         "y": targets[:, 1], "z": targets[:, 2], "std_x": np.full(n_targets, 3e-5),
         "std_y": np.full(n_targets, 3e-5), "std_z": np.full(n_targets, 4e-5),
         "n_touchups": np.bincount(touch["target_id"], minlength=n_targets)}
    )  # fmt: skip
    _write(run_dir / "targets.parquet", tgt_df, "targets")
    par: list[dict[str, Any]] = []
    for j in nominal.actuated:
        dt = origins[j.name][:3, 3] - j.T_parent_joint[:3, 3]
        for a, val in zip("xyz", dt, strict=True):
            ident = not (j.name == "joint_1" and a == "z")
            par.append(
                {"model": "full", "name": f"{j.name}.{a}", "kind": "kinematic", "joint": j.name,
                 "unit": "m", "nominal": 0.0, "value": val if ident else 0.0,
                 "std": 2e-5 if ident else np.nan, "identifiable": ident,
                 "held_reason": "" if ident else "along the base frame's z: not observable",
                 "estimated_index": len(par), "correlation": []}
            )  # fmt: skip
    for a, val in zip("xyz", p_pin, strict=True):
        par.append(
            {"model": "full", "name": f"pin.{a}", "kind": "pin", "joint": "", "unit": "m",
             "nominal": 0.0, "value": val, "std": 3e-5, "identifiable": True,
             "held_reason": "", "estimated_index": len(par), "correlation": []}
        )  # fmt: skip
    _write(run_dir / "parameters.parquet", pd.DataFrame(par), "parameters")
    cv = [
        {"model": m, "scheme": scheme, "fold": i % 3, "touchup_id": i,
         "target_id": int(touch["target_id"].iloc[i]), "n_train": 8,
         "ex": e[0], "ey": e[1], "ez": e[2], "error_mm": float(np.linalg.norm(e) * 1e3),
         "status": ""}
        for m, sc in (("offsets", 4e-4), ("full", 6e-5))
        for scheme in ("kfold", "loto")
        for i in range(8)
        for e in [rng.normal(0, sc, 3)]
    ]  # fmt: skip
    _write(run_dir / "crossval.parquet", pd.DataFrame(cv), "crossval")
    (run_dir / "calibrated.urdf").write_text(write_calibrated_urdf(urdf, origins, "flange", p_pin))
    # the fields identify.json carries (pipeline/stages/identify/stage.py), with made-up values
    held = [{"name": "joint_1.z", "reason": "along the base frame's z: not observable"}]
    identify: dict[str, Any] = {
        "model": "full",
        "best_model": "full",
        "model_description": "per-joint origin translations (demo)",
        "n_rows": int(len(touch)),
        "n_used": int(inl["inlier"].sum()),
        "n_targets": n_targets,
        "n_params": 18,
        "n_identified": 17,
        "dof": 10,
        "unidentifiable": [h["name"] for h in held],
        "held": held,
        "scale_held": not known_distance,
        "scale_note": "no known distance" if not known_distance else "identified",
        "cond": 412.5,
        "O1": 0.8,
        "O2": 0.0024,
        "O3": 0.12,
        "O4": 3e-4,
        "O5": 0.05,
        "rms_mm": 0.03,
        "max_mm": 0.05,
        "predicted_shape_rms_mm": 0.04,
        "predicted_shape_max_mm": 0.09,
        "predicted_absolute_rms_mm": 0.05,
        "predicted_absolute_max_mm": 0.11,
        "p_flange_pin": [float(v) for v in p_pin],
        "singular_values": [float(x) for x in np.geomspace(10, 0.02, 12)],
        "crossval": {
            "chosen_model": "full",
            "choice": "full: smallest k-fold RMS among completely cross-validated models",
            "models": {"full": {"train_rms_mm": 0.03}, "offsets": {"train_rms_mm": 0.35}},
        },
    }
    identify["models"] = {"full": {k: v for k, v in identify.items() if k != "crossval"}}
    (run_dir / "identify.json").write_text(json.dumps(identify, indent=1, sort_keys=True))
    meta = {
        "base_link": "base_link",
        "flange_link": "flange",
        "designated_u": str(d0[0]),
        "designated_v": str(d0[1]),
        "designated_size_px": str(d0[2]),
        "threshold_px": "0.5",
        "threshold_size_px": "0.5",
        "target_diameter_m": "0.01",
    }
    if known_distance:
        meta["known_distances"] = (
            f"0:{n_targets - 1}={np.linalg.norm(targets[-1] - targets[0]):.6f}"
        )
    rec_path = run_dir / "recording.mcap"
    if with_recording:
        _write_mcap(rec_path, images, t0)
    recording = {
        "path": str(rec_path) if with_recording else str(run_dir / "gone.mcap"),
        "urdf": urdf,
        "metadata": meta,
        "inferred": {"polarity": "dark_on_light (automatic, from 50 images)"},
        "joint_names": names,
        "base_link": "base_link",
        "flange_link": "flange",
        "image_topic": IMAGE_TOPIC,
        "n_images": len(images),
        "n_joint_states": 10 * len(images),
        "truncated": False,
        "warnings": [],
    }
    (run_dir / "recording.json").write_text(json.dumps(recording, indent=1, sort_keys=True))
    run: dict[str, Any] = {
        "stages": [
            {"stage": s, "status": "ran", "seconds": 0.1, "outputs": [], "note": ""}
            for s in ("ingest", "touchups", "outliers", "identify", "crossval")
        ]
    }
    (run_dir / "run.json").write_text(json.dumps(run, indent=1, sort_keys=True))
    return run_dir


def _write_mcap(path: Path, images: list[tuple[int, np.ndarray]], t0: int) -> None:
    from mcap_ros2.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/Image", _IMAGE_MSGDEF)
        for i, img in images:
            stamp = t0 + i * 200_000_000
            msg = {
                "header": {
                    "stamp": {"sec": stamp // 1_000_000_000, "nanosec": stamp % 1_000_000_000},
                    "frame_id": "camera",
                },
                "height": img.shape[0],
                "width": img.shape[1],
                "encoding": "mono8",
                "is_bigendian": 0,
                "step": img.shape[1],
                "data": img.tobytes(),
            }
            w.write_message(IMAGE_TOPIC, schema, msg, log_time=stamp, publish_time=stamp)
        w.finish()
