"""The bad-input catalogue (docs/robustness.md): every entry drives the real CLI in-process.

Each case checks the exit code, that stderr is exactly one line (the error, or
one warning for inputs that are read with a loss), and that the line names the
file and what is wrong with it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from mcap.writer import CompressionType
from test_robustness_data import (
    MS,
    NAMES,
    T0,
    H,
    W,
    chunk_spans,
    disc,
    q_of_t,
    raw_image_recording,
    relog,
    run_cli,
    tiny_recording,
    touchup_table,
)

from pipeline.io.artefacts import read_artefact

SAMPLE = Path(__file__).resolve().parent.parent / "datasets" / "samples" / "sample_lrmate.mcap"


def _run(rec: Path, out: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    return run_cli(["run", str(rec), "--out", str(out), "-q", "--no-report", *extra], capsys)


def _one_error(code: int, err: list[str], want_code: int, *needles: str) -> str:
    assert code == want_code, err
    assert len(err) == 1, err
    line = err[0]
    assert line.startswith("vtcal: error: "), line
    for n in needles:
        assert n in line, (n, line)
    return line


# --------------------------------------------------------------------------- recordings


@pytest.mark.parametrize(
    "kind,needle",
    [
        ("no_images", "no image messages"),
        ("no_joints", "no joint states on /joint_states"),
        ("no_urdf", "no URDF on /robot_description"),
        ("one_joint_state", "only one joint state"),
        ("unknown_encoding", "unknown image encoding 'yuv422'"),
        ("urdf_unparsable", "URDF does not parse"),
        ("urdf_joint_names", "does not have"),
        ("nan_joint", "non-finite position"),
        ("inf_joint", "non-finite position"),
    ],
)
def test_recording_bad_input_is_one_line_exit_2(tmp_path, capsys, kind, needle):
    rec = tmp_path / f"{kind}.mcap"
    kw: dict = {}
    bad_q = np.array([0.1, np.nan])
    if kind == "no_images":
        kw["images"] = []
    elif kind == "no_joints":
        kw["joints"] = []
    elif kind == "no_urdf":
        kw["urdf"] = None
    elif kind == "one_joint_state":
        kw["joints"] = [(T0, q_of_t(T0))]
    elif kind == "unknown_encoding":
        kw["encoding"] = "yuv422"
    elif kind == "urdf_unparsable":
        kw["urdf"] = '<robot name="x"><link name="a"/><joint'
    elif kind == "urdf_joint_names":
        kw["joint_names"] = ["shoulder", "elbow"]
    elif kind in ("nan_joint", "inf_joint"):
        if kind == "inf_joint":
            bad_q = np.array([np.inf, 0.2])
        kw["joints"] = [
            (T0 + k * 10 * MS, bad_q if k == 7 else q_of_t(T0 + k * 10 * MS)) for k in range(120)
        ]
    tiny_recording(rec, **kw)
    code, err = _run(rec, tmp_path / "out", capsys)
    _one_error(code, err, 2, str(rec), needle)


def test_not_an_mcap_empty_file_and_header_only(tmp_path, capsys):
    good = tiny_recording(tmp_path / "good.mcap").read_bytes()
    cases = {
        "text.mcap": (b"joint_1,joint_2\n0.1,0.2\n", "not an MCAP file"),
        "empty.mcap": (b"", "not an MCAP file"),
        "magic_only.mcap": (good[:8], "no URDF"),
        "header_only.mcap": (good[:40], "no URDF"),
    }
    for name, (data, needle) in cases.items():
        p = tmp_path / name
        p.write_bytes(data)
        code, err = _run(p, tmp_path / f"out_{name}", capsys)
        _one_error(code, err, 2, str(p), needle)
    code, err = _run(tmp_path / "nope.mcap", tmp_path / "o", capsys)
    _one_error(code, err, 2, "nope.mcap", "no such recording file")
    folder = tmp_path / "not_a_bag"
    folder.mkdir()
    code, err = _run(folder, tmp_path / "o", capsys)
    _one_error(code, err, 2, str(folder), "not a rosbag2 bag (no metadata.yaml)")


def test_wrong_topics_name_what_is_there(tmp_path, capsys):
    rec = tiny_recording(tmp_path / "rec.mcap")
    code, err = _run(rec, tmp_path / "o1", capsys, "--image-topic", "/cam/left")
    _one_error(code, err, 2, str(rec), "no image messages on /cam/left", "/camera/image_raw")
    code, err = _run(rec, tmp_path / "o2", capsys, "--joint-topic", "/arm/joints")
    _one_error(code, err, 2, str(rec), "no joint states on /arm/joints")
    code, err = _run(rec, tmp_path / "o3", capsys, "--base-link", "world")
    _one_error(code, err, 2, str(rec), "link 'world'")


def test_unknown_message_encoding(tmp_path, capsys):
    """A ROS 2 Image channel whose messages claim JSON encoding."""
    import json as _json

    from mcap.writer import Writer
    from support.mcap_write import msgdef

    rec = tiny_recording(tmp_path / "rec.mcap", n_img=0)
    bad = tmp_path / "json_images.mcap"
    relog(rec, bad, lambda topic, k, t: t)  # uncompressed copy, then add a JSON image channel
    data = bad.read_bytes()
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2")
        from mcap.reader import make_reader

        r = make_reader(__import__("io").BytesIO(data))
        s = r.get_summary()
        assert s is not None
        sid = {sc.id: w.register_schema(sc.name, sc.encoding, sc.data) for sc in s.schemas.values()}
        cid = {
            c.id: w.register_channel(c.topic, c.message_encoding, sid[c.schema_id])
            for c in s.channels.values()
        }
        img_schema = w.register_schema(
            "sensor_msgs/msg/Image", "ros2msg", msgdef("sensor_msgs/msg/Image", False).encode()
        )
        img_ch = w.register_channel("/camera/image_raw", "json", img_schema)
        for _, ch, m in r.iter_messages():
            w.add_message(cid[ch.id], log_time=m.log_time, data=m.data, publish_time=m.log_time)
        w.add_message(
            img_ch, log_time=T0 + 500 * MS, data=_json.dumps({"h": 1}).encode(), publish_time=T0
        )
        w.finish()
    code, err = _run(bad, tmp_path / "out", capsys)
    _one_error(code, err, 2, str(bad), "message encoding 'json'", "/camera/image_raw")


def test_truncated_tiny_recording_is_a_warning(tmp_path, capsys):
    rec = tiny_recording(
        tmp_path / "rec.mcap", n_img=6, compression=CompressionType.NONE, chunk_size=4000
    )
    data = rec.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    code, err = _run(cut, tmp_path / "out", capsys, "--until", "ingest")
    assert code == 0 and len(err) == 1, err
    assert err[0].startswith("vtcal: warning: ") and str(cut) in err[0]
    assert "truncated recording" in err[0] and "incomplete record" in err[0]
    info = json.loads((tmp_path / "out" / "recording.json").read_text())
    assert info["truncated"] and 0 < info["n_images"] < 6


def test_truncated_sample_still_calibrates(tmp_path, capsys):
    """The recorder killed at 70 %: a target is never reached; the run drops its known
    distance (noted) and calibrates from what is there, with one warning line."""
    cut = tmp_path / "sample_cut.mcap"
    data = SAMPLE.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    code, err = _run(cut, tmp_path / "out", capsys, "--until", "identify", "--model", "offsets")
    assert code == 0, err
    assert len(err) == 1 and "truncated recording" in err[0] and "%" in err[0], err
    summary = json.loads((tmp_path / "out" / "identify.json").read_text())
    assert any("no target" in d for d in summary["distances_dropped"])


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.ZSTD])
def test_chunk_failing_its_crc_is_skipped_with_a_warning(tmp_path, capsys, compression):
    rec = tiny_recording(tmp_path / "rec.mcap", n_img=6, compression=compression, chunk_size=4000)
    data = bytearray(rec.read_bytes())
    spans = chunk_spans(bytes(data))
    assert len(spans) >= 3
    a, b = spans[len(spans) // 2]
    data[b - 20] ^= 0x5A  # inside the chunk's records (its tail)
    bad = tmp_path / "crc.mcap"
    bad.write_bytes(bytes(data))
    code, err = _run(bad, tmp_path / "out", capsys, "--until", "ingest")
    # the skipped chunk, and (a consequence) images with a joint-state gap: warnings only
    assert code == 0 and all(e.startswith("vtcal: warning: ") for e in err), err
    assert str(bad) in err[0] and "1 chunk(s) failed their CRC" in err[0]
    frames = read_artefact(tmp_path / "out" / "frames.parquet", "frames")
    assert len(frames) <= 6


def test_zero_and_wrong_size_images_are_flagged(tmp_path, capsys):
    good = disc(30.0, 22.0).tobytes()
    rec = raw_image_recording(
        tmp_path / "sizes.mcap",
        [
            {"height": H, "width": W, "step": W, "data": good},
            {"height": 0, "width": 0, "step": 0, "data": b""},  # zero-size
            {"height": H, "width": W, "step": W, "data": good[:-W]},  # one row short
            {"height": H, "width": W, "step": W, "data": good + b"\0" * 7},  # too long
            {"height": H, "width": W, "step": W // 2, "data": good[: H * W // 2]},  # step < width
        ],
    )
    code, err = _run(rec, tmp_path / "out", capsys, "--until", "ingest")
    assert code == 0 and len(err) == 1, err
    assert "4 of 5 images" in err[0] and "do not decode" in err[0] and str(rec) in err[0]
    det = read_artefact(tmp_path / "out" / "detections.parquet", "detections")
    assert len(det) == 5  # never delete data: every frame kept
    reasons = det["reason"].tolist()
    assert not reasons[0].startswith("decode_failed")
    assert all(r.startswith("decode_failed") for r in reasons[1:]), reasons
    assert "step*height" in reasons[2]
    # every image broken: the run stops at the first stage that needs a detection
    rec2 = raw_image_recording(
        tmp_path / "all_zero.mcap", [{"height": 0, "width": 0, "step": 0, "data": b""}] * 3
    )
    code, err = _run(rec2, tmp_path / "out2", capsys)
    _one_error(code, err, 2, str(rec2), "no detections")


def test_backwards_and_duplicate_stamps_are_warned(tmp_path, capsys):
    rec = tiny_recording(tmp_path / "rec.mcap", n_img=5)

    def shuffle(topic: str, k: int, t: int) -> int:
        if topic == "/joint_states" and k == 50:
            return t - 200 * MS  # written 0.2 s late: stamps go backwards in log order
        if topic == "/camera/image_raw" and k == 3:
            return t - 400 * MS  # image 3 logged before image 2
        return t

    bad = tmp_path / "order.mcap"
    relog(rec, bad, shuffle)
    code, err = _run(bad, tmp_path / "out", capsys, "--until", "ingest")
    assert code == 0, err
    assert any("/joint_states: 1 header stamps go backwards" in e for e in err), err
    assert any("/camera/image_raw: 1 image stamps go backwards" in e for e in err), err
    frames = read_artefact(tmp_path / "out" / "frames.parquet", "frames")
    assert len(frames) == 5
    # interpolation is on sorted stamps: joints at the image stamps are still right
    q = frames[NAMES].to_numpy()
    q_true = np.array([q_of_t(int(t)) for t in frames["stamp_ns"]])
    assert np.abs(q - q_true).max() < 1e-9

    dup = tmp_path / "dup.mcap"
    tiny_recording(
        dup, joints=[(T0 + (k // 2) * 10 * MS, q_of_t(T0 + (k // 2) * 10 * MS)) for k in range(240)]
    )
    code, err = _run(dup, tmp_path / "out_dup", capsys, "--until", "ingest")
    assert code == 0 and len(err) == 1 and "120 repeat an earlier stamp" in err[0], err


# --------------------------------------------------------------------------- touch-up tables


@pytest.fixture(scope="module")
def table_and_urdf(tmp_path_factory):
    table, urdf = touchup_table(seed=3)
    d = tmp_path_factory.mktemp("tables")
    (d / "robot.urdf").write_text(urdf)
    return table, d / "robot.urdf"


def _identify(capsys, table_path: Path, urdf: Path, out: Path, *extra: str):
    return run_cli(
        [
            "identify",
            str(table_path),
            "--urdf",
            str(urdf),
            "--out",
            str(out),
            "--model",
            "offsets",
            *extra,
        ],
        capsys,
    )


def _table_case(kind: str, t: pd.DataFrame, p: Path) -> None:
    if kind == "missing_column":
        t.drop(columns=["joint_3"]).to_csv(p, index=False)
    elif kind == "wrong_joint_names":
        t.rename(columns={f"joint_{i}": f"axis{i}" for i in range(1, 7)}).to_csv(p, index=False)
    elif kind == "text_in_joint":
        t.assign(joint_4="abc").to_csv(p, index=False)
    elif kind == "text_in_id":
        t.assign(touchup_id="first").to_csv(p, index=False)
    elif kind == "duplicate_id":
        t.assign(touchup_id=0).to_csv(p, index=False)
    elif kind == "binary_garbage":
        p.write_bytes(np.random.default_rng(0).bytes(2000))
    elif kind == "latin1":
        p.write_bytes(
            t.to_csv(index=False).replace("target_id", "target_id_\xe9").encode("latin-1")
        )
    elif kind == "empty":
        p.write_bytes(b"")
    elif kind == "header_only":
        p.write_text(",".join(t.columns) + "\n")
    elif kind == "parquet_garbage":
        p.write_bytes(b"PAR1" + np.random.default_rng(1).bytes(500))


@pytest.mark.parametrize(
    "kind,suffix,needle",
    [
        ("missing_column", ".csv", "missing column(s) ['joint_3']"),
        ("wrong_joint_names", ".csv", "missing column(s) ['joint_1'"),
        ("text_in_joint", ".csv", "column 'joint_4' row 0: 'abc' is not a number"),
        ("text_in_id", ".csv", "column 'touchup_id' row 0: 'first' is not a number"),
        ("duplicate_id", ".csv", "touchup_id 0 appears more than once"),
        ("binary_garbage", ".csv", "not a text CSV"),
        ("latin1", ".csv", "byte 0xe9"),
        ("empty", ".csv", "not a readable touch-up table"),
        ("header_only", ".csv", "has no rows"),
        ("parquet_garbage", ".parquet", "not a readable touch-up table"),
    ],
)
def test_table_bad_input_is_one_line_exit_2(tmp_path, capsys, table_and_urdf, kind, suffix, needle):
    table, urdf = table_and_urdf
    p = tmp_path / f"{kind}{suffix}"
    _table_case(kind, table.copy(), p)
    code, err = _identify(capsys, p, urdf, tmp_path / "out")
    _one_error(code, err, 2, str(p), needle)
    assert not (tmp_path / "out" / "parameters.parquet").exists()


def test_table_in_utf16_or_with_semicolons_is_read(tmp_path, capsys, table_and_urdf):
    table, urdf = table_and_urdf
    ref = tmp_path / "ref.csv"
    table.to_csv(ref, index=False)
    code, err = _identify(capsys, ref, urdf, tmp_path / "ref")
    assert code == 0, err
    want = read_artefact(tmp_path / "ref" / "parameters.parquet", "parameters")
    for name, data in {
        "utf16.csv": table.to_csv(index=False).encode("utf-16"),
        "bom.csv": b"\xef\xbb\xbf" + table.to_csv(index=False).encode(),
        "semicolon.csv": table.to_csv(index=False, sep=";").encode(),
    }.items():
        p = tmp_path / name
        p.write_bytes(data)
        code, err = _identify(capsys, p, urdf, tmp_path / f"out_{name}")
        assert code == 0, (name, err)
        got = read_artefact(tmp_path / f"out_{name}" / "parameters.parquet", "parameters")
        pd.testing.assert_frame_equal(got, want)


def test_nan_inf_and_huge_values_flag_their_rows(tmp_path, capsys, table_and_urdf):
    table, urdf = table_and_urdf
    t = table.copy()
    t.loc[1, "joint_2"] = np.nan
    t.loc[2, "joint_5"] = np.inf
    t.loc[3, "joint_1"] = 1e300
    t.loc[4, "dx_flange"] = 1e30
    t.loc[5, "weight"] = 1e300
    p = tmp_path / "values.csv"
    t.to_csv(p, index=False)
    code, err = _identify(capsys, p, urdf, tmp_path / "out")
    assert code == 0, err
    res = read_artefact(tmp_path / "out" / "residuals.parquet", "residuals")
    res = res[res.model == "offsets"].set_index("touchup_id")
    reasons = res.loc[[1, 2, 3, 4, 5], "reason"].tolist()
    assert "joint position missing" in reasons[0] and "joint position missing" in reasons[1]
    assert "beyond" in reasons[2] and "correction beyond" in reasons[3]
    assert "weight above" in reasons[4]
    assert not res.loc[[1, 2, 3, 4, 5], "used"].any() and res["used"].sum() == len(t) - 5


def test_unparsable_urdf_names_the_file(tmp_path, capsys, table_and_urdf):
    table, _ = table_and_urdf
    p = tmp_path / "t.csv"
    table.to_csv(p, index=False)
    bad = tmp_path / "bad.urdf"
    bad.write_text('<robot name="r"><link name="a"></robot')
    for extra in ([], ["--base-link", "base_link", "--flange-link", "flange"]):
        code, err = _identify(capsys, p, bad, tmp_path / "out", *extra)
        _one_error(code, err, 2, str(bad), "URDF does not parse")


# --------------------------------------------------------------------------- exit 3


def test_no_touchup_converged_and_too_few_exit_3_distinct_from_bad_input(
    tmp_path, capsys, table_and_urdf
):
    table, urdf = table_and_urdf
    none = tmp_path / "none.csv"
    table.assign(converged=False).to_csv(none, index=False)
    code, err = _identify(capsys, none, urdf, tmp_path / "o1")
    _one_error(code, err, 3, "no usable touch-ups", f"{len(table)} not converged")
    few = tmp_path / "few.csv"
    pd.concat([table[table.target_id == 0].head(4), table[table.target_id == 1].head(3)]).to_csv(
        few, index=False
    )
    code, err = _identify(capsys, few, urdf, tmp_path / "o2", "--model", "full")
    _one_error(code, err, 3, "add at least")
    single = tmp_path / "single.csv"
    table[table.target_id == 0].to_csv(single, index=False)
    code, err = _identify(capsys, single, urdf, tmp_path / "o3")
    _one_error(code, err, 3, "single target")
    # and bad input is 2, not 3
    code, err = _identify(capsys, tmp_path / "none.csv", tmp_path / "none.csv", tmp_path / "o4")
    assert code == 2 and len(err) == 1, err


def test_usage_errors_are_one_line_exit_2(tmp_path, capsys):
    f = tmp_path / "t.csv"
    f.write_text("touchup_id\n1\n")
    for args, needle in [
        (["identify", str(f), "--urdf", str(f), "--out", str(f)], "is a file"),
        (["run", str(f), "--out", str(tmp_path / "o"), "--until", "nope"], "'nope'"),
        (["run", str(f), "--bogus"], "No such option"),
        (["frobnicate"], "No such command"),
    ]:
        code, err = run_cli(args, capsys)
        _one_error(code, err, 2, needle, "--help")


def test_compressed_images_unknown_format_or_corrupt(tmp_path, capsys):
    import cv2
    from test_robustness_data import compressed_recording

    png = cv2.imencode(".png", disc(30.0, 22.0))[1].tobytes()
    rec = compressed_recording(tmp_path / "gif.mcap", "gif", [png, png])
    code, err = _run(rec, tmp_path / "o1", capsys)
    _one_error(code, err, 2, str(rec), "unknown compressed image format 'gif'")
    # a PNG cut short does not decode: flagged (kept), one warning
    rec = compressed_recording(tmp_path / "cut.mcap", "png", [png, png[: len(png) // 2], png])
    code, err = _run(rec, tmp_path / "o2", capsys, "--until", "ingest")
    assert code == 0 and len(err) == 1 and "1 of 3 images" in err[0], err


@pytest.mark.parametrize(
    "setting,needle",
    [
        ("polarity=purple", "polarity 'purple'"),
        ("designated_u=nan", "designated_u='nan' is not a finite number"),
        ("designated_size_px=abc", "designated_size_px='abc' is not a number"),
        ("threshold_px=-1", "threshold_px='-1' must be > 0"),
        ("known_distances=0:1=abc", "known distance '0:1=abc'"),
    ],
)
def test_bad_metadata_values_are_one_line_exit_2(tmp_path, capsys, setting, needle):
    rec = tiny_recording(tmp_path / "rec.mcap")
    code, err = _run(rec, tmp_path / "out", capsys, "--set", setting)
    _one_error(code, err, 2, needle)
