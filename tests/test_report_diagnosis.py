"""The report's camera and target self-diagnosis: trends a residual can show, and what it cannot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.kinematics.chain import fk, load_chain
from pipeline.report.data import RunData
from pipeline.report.diagnosis import (
    along_view_trend,
    camera_section,
    flat_field_rows,
    plate_basis,
    size_correction_rows,
)
from pipeline.robots import builtin_urdf

PIN = np.array([0.01, -0.02, 0.25])


def _run(tmp_path: Path, amp_m: float, tilt_m: float, n: int = 36, seed: int = 3) -> RunData:
    """A run folder's artefacts in memory: residuals along the view with a 2-beta and tilt term."""
    urdf = builtin_urdf("lrmate")
    cal = urdf.replace(
        "</robot>",
        '<link name="virtual_pin"/><joint name="virtual_pin_joint" type="fixed">'
        '<parent link="flange"/><child link="virtual_pin"/>'
        f'<origin xyz="{PIN[0]} {PIN[1]} {PIN[2]}" rpy="0 0 0"/></joint></robot>',
    )
    chain = load_chain(urdf, "base_link", "flange")
    names = chain.joint_names
    rng = np.random.default_rng(seed)
    rows, res = [], []
    for i in range(n):
        k = i % 3
        q = np.array([0.3 * k - 0.3, 0.2, -0.1, 0.0, -1.2, 0.0]) + rng.normal(0, 0.25, 6)
        R = fk(chain, q)[:3, :3]
        view_f = np.array([0.0, 0.0, 1.0])
        tilt = np.radians(rng.uniform(5, 35))
        phi = rng.uniform(0, 2 * np.pi)
        long_f = np.array([np.cos(phi), np.sin(phi), 0.0])
        v_b, a_b = R @ view_f, R @ long_f
        rows.append(
            {
                "touchup_id": i,
                "target_id": k,
                "axis_ratio": np.cos(tilt),
                **{f"view_{c}_flange": view_f[j] for j, c in enumerate("xyz")},
                **{f"long_axis_{c}_flange": long_f[j] for j, c in enumerate("xyz")},
                **dict(zip(names, q, strict=True)),
            }
        )
        # the diagnosis measures beta in a plate basis built from the target's mean view:
        # inject the signal through the same construction, after the loop
        res.append((i, k, v_b, a_b, tilt))
    tu = pd.DataFrame(rows)
    vb = np.array([r[2] for r in res])
    ab = np.array([r[3] for r in res])
    r_view = np.zeros(n)
    for k in range(3):
        m = np.arange(n) % 3 == k
        e1, e2 = plate_basis(vb[m].mean(0))
        beta = np.arctan2(ab[m] @ e2, ab[m] @ e1)
        tilt = np.array([r[4] for r in res])[m]
        r_view[m] = amp_m * np.cos(2 * beta - 0.4) + tilt_m * (1 - np.cos(tilt)) + 1e-5 * k
    r_view += rng.normal(0, 1e-6, n)
    resid = pd.DataFrame(
        {
            "model": "full",
            "touchup_id": np.arange(n),
            "target_id": np.arange(n) % 3,
            "used": True,
            "rx": r_view * vb[:, 0],
            "ry": r_view * vb[:, 1],
            "rz": r_view * vb[:, 2],
        }
    )
    rec = {"joint_names": names, "base_link": "base_link", "flange_link": "flange",
           "camera": {"response": "srgb", "response_source": "estimated",
                      "note": "srgb (estimated ...)", "illumination_gradient": 0.12,
                      "illumination_gradient_max": 0.18, "n_images": 12}}  # fmt: skip
    return RunData(
        run_dir=tmp_path,
        recording=rec,
        identify={"best_model": "full"},
        touchups=tu,
        residuals=resid,
        calibrated_urdf=cal,
    )


def test_a_roll_dependent_size_error_is_found_and_flagged(tmp_path: Path) -> None:
    tr = along_view_trend(_run(tmp_path, amp_m=40e-6, tilt_m=0.0))
    assert tr is not None and tr["n"] == 36
    assert abs(tr["roll_amp_m"] - 40e-6) < 2e-6
    assert abs(tr["tilt_term_m"]) < 5e-6
    sec = camera_section(_run(tmp_path, amp_m=40e-6, tilt_m=0.0))
    status = {r["effect"]: r["status"] for r in sec["rows"]}
    assert status["size bias against roll"] == "warn"
    assert status["size bias against tilt"] == "ok"
    assert any("depend on the roll" in w for w in sec["warnings"])
    assert sec["svg"].startswith("<svg")


def test_a_tilt_dependent_size_error_is_found(tmp_path: Path) -> None:
    tr = along_view_trend(_run(tmp_path, amp_m=0.0, tilt_m=400e-6))
    assert tr is not None
    assert abs(tr["tilt_term_m"] - 400e-6) < 20e-6
    assert tr["roll_amp_m"] < 3e-6


def test_clean_runs_raise_no_flag_and_say_what_was_found(tmp_path: Path) -> None:
    sec = camera_section(_run(tmp_path, amp_m=0.0, tilt_m=0.0))
    assert not sec["warnings"]
    found = {r["effect"]: r["found"] for r in sec["rows"]}
    assert found["camera response"].startswith("srgb")
    assert found["illumination across the target"].startswith("12.0 %")


def test_an_assumed_response_is_warned_about(tmp_path: Path) -> None:
    data = _run(tmp_path, amp_m=0.0, tilt_m=0.0)
    assert data.recording is not None
    data.recording["camera"] = {"response": "linear", "response_source": "assumed",
                                "note": "linear (assumed: the edges are too sharp)"}  # fmt: skip
    sec = camera_section(data)
    assert any("could not be estimated" in w for w in sec["warnings"])


def test_a_saturated_edge_is_warned_about(tmp_path: Path) -> None:
    data = _run(tmp_path, amp_m=0.0, tilt_m=0.0)
    assert data.recording is not None
    data.recording["camera"] = {**data.recording["camera"], "saturated_fraction": 0.2}
    sec = camera_section(data)
    assert any("saturated" in w and "20 %" in w for w in sec["warnings"])


def test_a_large_mean_size_correction_is_warned_about() -> None:
    """Touch-ups that all stopped ~1.4 mm off along the view: the pin error it can leave."""
    n = 12
    tu = pd.DataFrame(
        {
            "touchup_id": np.arange(n),
            "converged": True,
            "lost": False,
            "dx_flange": 1e-5,
            "dy_flange": -2e-5,
            "dz_flange": np.full(n, 1.4e-3),
            "e_s_px": 0.45,
        }
    )
    rows, warn = size_correction_rows(tu)
    assert rows[0]["status"] == "warn" and "1.40 mm" in rows[0]["found"]
    assert warn and "14 um" in warn[0]
    tu["dz_flange"] = 1e-4
    rows, warn = size_correction_rows(tu)
    assert rows[0]["status"] == "ok" and not warn


def test_clipped_edges_say_how_much_they_were_corrected() -> None:
    from pipeline.report.diagnosis import clip_rows

    det = pd.DataFrame(
        {
            "found": [True, True, True, False],
            "clip_correction_px": [0.0, 0.31, 0.35, np.nan],
        }
    )
    rows = clip_rows(det)
    assert len(rows) == 1 and "2 of 3 detections" in rows[0]["found"]
    assert "+0.330 px" in rows[0]["found"]
    det["clip_correction_px"] = 0.0
    assert clip_rows(det) == []


def test_the_correction_frame_is_shown_from_identify_json() -> None:
    from pipeline.report.diagnosis import frame_rows

    ident = {
        "best_model": "full",
        "models": {
            "full": {
                "correction_frame": {
                    "method": "calibrated",
                    "matrix_minus_identity": [[0.0, 0.003, 0.0], [0.0, 0.0, -0.0012], [0, 0, 0]],
                    "rms_change_um": 1.5,
                    "max_change_um": 4.25,
                }
            }
        },
    }
    rows = frame_rows(ident)
    assert len(rows) == 1
    assert "3.0 per thousand" in rows[0]["found"] and "4.25 um" in rows[0]["found"]
    assert frame_rows({"best_model": "full", "models": {"full": {}}}) == []
    assert frame_rows(None) == []


def test_the_camera_settle_the_touchups_stage_found_is_shown(tmp_path: Path) -> None:
    """touchups.parquet's ``vtcal.settle`` (the repeated final captures' scatter by place
    and the weights used) becomes two rows of the camera section."""
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.report.diagnosis import settle_rows

    settle = {
        "centre": {
            "tested": True,
            "weighted": True,
            "p_value": 1e-9,
            "scatter_px": [0.011, 0.028],
            "weights": [1.0, 0.25, 0.04],
        },
        "size": {"tested": True, "weighted": False, "p_value": 0.4, "scatter_px": [0.01, 0.01]},
    }
    table = pa.table({"touchup_id": [0]})
    path = tmp_path / "touchups.parquet"
    pq.write_table(
        table.replace_schema_metadata({b"vtcal.settle": json.dumps(settle).encode()}), path
    )
    rows = settle_rows(RunData(run_dir=tmp_path))
    assert [r["effect"] for r in rows] == ["camera settle (centre)", "camera settle (long axis)"]
    assert "still swinging" in rows[0]["found"] and "0.011, 0.028 px" in rows[0]["found"]
    assert "1.00, 0.25, 0.04" in rows[0]["found"]
    assert rows[1]["found"].startswith("settled") and "plain means" in rows[1]["found"]
    assert "one-mode" not in rows[0]["found"]  # written before the swing fit: nothing said
    settle["centre"]["swing"] = {
        "n": 36,
        "r": 0.5,
        "delta_deg": 50.0,
        "spacing_s": 0.21,
        "swing_last_px": 0.0061,
        "shift_px": 0.007,
    }
    pq.write_table(
        table.replace_schema_metadata({b"vtcal.settle": json.dumps(settle).encode()}), path
    )
    found = settle_rows(RunData(run_dir=tmp_path))[0]["found"]
    assert "one-mode fit of the swing over 36 touch-ups" in found and "0.006 px RMS" in found
    assert "weights 1.00, 0.25, 0.04 (the last first), used for the long axis' angle" in found
    assert "decay 0.50 and phase step 50 deg" in found
    settle["centre"]["swing"] = None
    pq.write_table(
        table.replace_schema_metadata({b"vtcal.settle": json.dumps(settle).encode()}), path
    )
    assert "not used" in settle_rows(RunData(run_dir=tmp_path))[0]["found"]
    path.unlink()
    assert settle_rows(RunData(run_dir=tmp_path)) == []  # no touch-ups table: nothing to say


def test_the_sensor_gain_pattern_ingest_found_is_shown() -> None:
    """Found and corrected, not found, and not estimated: each says which."""
    applied = flat_field_rows(
        {
            "flat_field": {
                "applied": True,
                "rounds": 2,
                "note": "fixed gain pattern (PRNU) 0.99 % found (z = 33.3, flat against edge samples, "
                "197 images, 11700 pixels): corrected",
            }
        }  # fmt: skip
    )
    assert applied[0]["effect"] == "sensor gain pattern (PRNU)"
    assert "0.99 %" in applied[0]["found"] and "2 rounds" in applied[0]["found"]
    none = flat_field_rows(
        {"flat_field": {"applied": False, "note": "no fixed gain pattern (z = 0.3)"}}
    )
    assert none[0]["found"].startswith("no fixed gain pattern") and none[0]["status"] == "ok"
    over = flat_field_rows(
        {"flat_field": {"applied": False, "note": "not estimated: 3 clean images"}}
    )
    assert over[0]["status"] == "na"
    assert flat_field_rows({"response": "linear"}) == []  # runs from before it: no row
