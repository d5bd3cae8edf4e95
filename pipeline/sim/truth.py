"""The simulator's ground truth (``NAME.mcap.truth.json``; spec ``recording.md``).

:func:`index_images` turns the image positions the session noted into the
image topic's indices in log-time order once the file is written;
:func:`truth_of` assembles the truth dictionary (its layout is the conformance
sample's; tests and benchmarks read it, the pipeline never does).
"""

from __future__ import annotations

from typing import Any

from pipeline.kinematics.se3 import F64
from pipeline.sim.scenario import Scenario
from pipeline.sim.session import Session

NOTES = (
    "times: *_ns are MCAP log/stamp nanoseconds; *_s are seconds from the recording start. "
    "image_indices count the image topic's messages in log-time order from 0; mcap_sequence is "
    "the Message record's sequence field = index of the message in the file's log-time order. "
    "q are noise-free encoder angles (the joint_states add encoder noise). pin_miss_mm = true pin "
    "- true target centre at the end of the touch-up. Target labels: 0, 1, ... in the order the "
    "run first touches them up (known_distances use labels). visible_fraction: share of the "
    "target disc's image inside the image (0 when occluded). true_ellipse = [u, v, long_axis_px, "
    "short_axis_px, angle_rad] fitted to the exactly projected contour (pose at mid-exposure). "
    "sim_detection is the simulated controller's own (u, v, s)."
)


def index_images(sess: Session) -> None:
    """Replace the image positions in the touch-up, probe and fault records by image indices.

    A position counts captures in the order they were taken; an index counts the
    image topic's messages in log-time order (known once they are written).
    """
    img_by_pos = sess.images
    order = sorted(range(len(img_by_pos)), key=lambda i: img_by_pos[i]["log_time_ns"])
    pos_to_index = {p: img_by_pos[p]["index"] for p in order}
    for tu in sess.touchups:
        tu["image_indices"] = [pos_to_index[p] for p in tu["image_indices"]]
        tu["converged_image_indices"] = [pos_to_index[p] for p in tu["converged_image_indices"]]
    for pr in sess.probes:
        pr["image_indices"] = [pos_to_index[p] for p in pr["image_indices"]]
        pr["base_image_index"] = pos_to_index[pr["base_image_index"]]
    tu_by_index = {tu["index"]: tu for tu in sess.touchups}
    for fl in sess.faults:
        if fl["type"] == "target_knocked":
            imgs = [i for k in fl["touchups_after"] for i in tu_by_index[k]["image_indices"]]
        elif fl["type"] == "joint_state_gap":
            continue
        else:
            imgs = [pos_to_index[p] for p in fl.pop("_images")]
        fl["image_indices"] = imgs
        fl["image_log_times_ns"] = [sess.images[pos_of(sess, i)]["log_time_ns"] for i in imgs]
    sess.images.sort(key=lambda r: r["index"])


def pos_of(sess: Session, index: int) -> int:
    for p, r in enumerate(sess.images):
        if r["index"] == index:
            return p
    raise KeyError(index)


def truth_of(
    sess: Session,
    plan: list[tuple[int, F64]],
    labels: dict[int, int],
    known: list[dict[str, Any]],
    metadata: dict[str, str],
) -> dict[str, Any]:
    sc = sess.sc
    cell = sess.cell
    rob = sess.robot
    assert rob is not None
    cam = cell.camera
    return {
        "robot": sc.robot.name if not sc.robot.urdf else sc.robot.urdf,
        "seed": sess.seed,
        "scenario": sc.name,
        "faults_enabled": sc.faults.any(),
        "options": {
            "poses_per_target": sc.poses.per_target,
            "targets": sc.targets.count,
            "faults": sc.faults.any(),
            "polarity": sc.targets.polarity,
            "compressed": image_encoding(sc) if sess.compressed else None,
            "known_distance": bool(known),
            "truncate_at": None,
            "scenario": sc.to_dict(),
        },
        "image_topic": sess.image_topic,
        "image_encoding": image_encoding(sc),
        "metadata": metadata,
        "known_distances": known,
        "truncated": None,
        "joint_names": cell.nominal.joint_names,
        "base_link": sc.robot.base_link,
        "flange_link": sc.robot.flange_link,
        "nominal_urdf": cell.nominal_urdf,
        "true_urdf": cell.true_urdf,
        "true_urdf_with_pin": cell.true_urdf_with_pin,
        "deviations": cell.deviations,
        "camera": {
            "model": "pinhole, radial distortion x_d = x (1 + k1 r^2 + k2 r^4), OpenCV axes",
            **cam.to_dict(),
            "T_flange_camera": cell.T_flange_camera.tolist(),
        },
        "p_vt_flange": cell.p_vt_flange.tolist(),
        "p_vt_camera": cell.p_vt_camera.tolist(),
        "standoff_m": float(cell.p_vt_camera[2]),
        "designated": {"u": cell.u0, "v": cell.v0, "s0": cell.s0},
        "targets": [
            {
                "id": t.id,
                "label": labels.get(t.id),
                "centre": t.initial.tolist(),
                "normal": t.normal.tolist(),
                "diameter_m": sc.targets.diameter_m,
                "plate_radius_m": sc.targets.plate_radius_m,
                "history": [
                    {
                        "from_s": 0.0,
                        "from_ns": int(sc.timing.start_ns),
                        "centre": t.initial.tolist(),
                    }
                ]
                + t.history,
            }
            for t in cell.targets
        ],
        "touchups": sess.touchups,
        "probes": sess.probes,
        "images": sess.images,
        "counts": {
            "joint_states": rob.emitted,
            "images": len(sess.images),
            "touchups": len(sess.touchups),
        },
        "noise": {
            "encoder_rad": sc.timing.encoder_noise_rad,
            "image_grey_sigma": sc.camera.noise_sigma,
            "blur_sigma_px": sc.camera.blur_sigma_px,
            "vignetting": sc.camera.vignetting,
            "levels": {
                "target": float(sess.levels[0]),
                "plate": float(sess.levels[1]),
                "table": float(sess.background),
            },
        },
        "faults": sess.faults,
        "optics": sess.optics.truth() if sess.optics.active else None,
        "notes": NOTES,
    }


def image_encoding(sc: Scenario) -> str:
    """What the image topic carries: ``jpeg``, ``png``, ``bgr8`` (Bayer, raw) or ``mono8``."""
    if sc.optics.jpeg_quality > 0:
        return "jpeg"
    if sc.camera.image == "png":
        return "png"
    return "bgr8" if sc.optics.bayer else "mono8"
