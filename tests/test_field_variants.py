"""Field recordings as they come (issue 34): each variant read right or refused in one line.

Every variant is written as a recorder would write it: a small simulated
recording is copied message by message (``support.field_variants.rewrite``)
with the one difference, and the CLI runs on it in-process. Every URDF, JSON
and Parquet file a run writes must parse; a refusal must leave one
``vtcal: error:`` line on stderr and nothing partial in ``--out``.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from mcap.writer import CompressionType, IndexType
from support.field_variants import (
    SMALL_TOML,
    png_grey,
    raw_image,
    rewrite,
    simulated,
    upscaled,
    written_files_parse,
    xcdr2,
)
from test_robustness_data import run_cli


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    return simulated(tmp_path_factory.mktemp("field"))


#: the verdict's own warnings (pipeline.stages.outliers.adequacy: the calibration's trust, the
#: same on the reference recording of the tiny scene), not warnings about reading it
_TRUST = (
    "vtcal: warning: systematic error likely",
    "vtcal: warning: camera response assumed",
    "vtcal: warning: the camera's curve",
    "vtcal: warning: touch-ups covered",
)


def _run(rec: Path, out: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    code, err = run_cli(["run", str(rec), "--out", str(out), "-q", "--no-report", *extra], capsys)
    return code, [ln for ln in err if not ln.startswith(_TRUST)]


def _one_error(code: int, err: list[str], want: int, *needles: str) -> str:
    assert code == want, err
    assert len(err) == 1, err
    assert err[0].startswith("vtcal: error: "), err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]


# --------------------------------------------------------------- 1: URDF with a BOM


def test_urdf_with_byte_order_mark_is_read_and_written_well_formed(sim, tmp_path, capsys):
    rec, _ = sim

    def bom(topic: str, msg: dict) -> dict:
        if topic == "/robot_description":
            msg["data"] = "\ufeff" + msg["data"]
        return msg

    variant = rewrite(rec, tmp_path / "bom.mcap", bom)
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys)
    assert code == 0, err
    written = written_files_parse(out)
    assert "calibrated.urdf" in written and "recording.json" in written
    urdf = json.loads((out / "recording.json").read_text())["urdf"]
    assert not urdf.startswith("\ufeff")


# --------------------------------------------------------------- 2: a gripper, no flange_link

GRIPPER = """
  <link name="hand"/><link name="finger_left"/><link name="finger_right"/>
  <joint name="hand_joint" type="fixed">
    <parent link="flange"/><child link="hand"/><origin xyz="0 0 0.06" rpy="0 0 0"/>
  </joint>
  <joint name="finger_left_joint" type="prismatic">
    <parent link="hand"/><child link="finger_left"/><origin xyz="0 0.01 0.05" rpy="0 0 0"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="20" velocity="0.2"/>
  </joint>
  <joint name="finger_right_joint" type="prismatic">
    <parent link="hand"/><child link="finger_right"/><origin xyz="0 -0.01 0.05" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/><limit lower="0" upper="0.04" effort="20" velocity="0.2"/>
    <mimic joint="finger_left_joint"/>
  </joint>
</robot>"""


def test_gripper_fingers_that_never_move_are_not_the_flange(sim, tmp_path, capsys):
    rec, truth = sim

    def gripper(topic: str, msg: dict) -> dict:
        if topic == "/robot_description":
            msg["data"] = msg["data"].replace("</robot>", GRIPPER)
        elif topic == "/joint_states":  # the gripper's state on the arm's topic, held open
            msg["name"] = [*msg["name"], "finger_left_joint", "finger_right_joint"]
            msg["position"] = [*msg["position"], 0.02, 0.02]
            if msg["velocity"]:
                msg["velocity"] = [*msg["velocity"], 0.0, 0.0]
            if msg["effort"]:
                msg["effort"] = [*msg["effort"], 0.0, 0.0]
        return msg

    def no_links(md: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in md.items() if k not in ("flange_link", "base_link")}

    variant = rewrite(rec, tmp_path / "gripper.mcap", gripper, no_links)
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys)
    assert code == 0, err
    written_files_parse(out)
    info = json.loads((out / "recording.json").read_text())
    assert info["flange_link"] == truth["flange_link"] == "flange"
    why = info["inferred"]["flange_link"]
    assert "joint_6" in why and "finger_left_joint" in why and "never move" in why, why
    assert any("flange" in ln and "never move" in ln for ln in err), err
    assert '<parent link="flange" />' in (out / "calibrated.urdf").read_text()


# --------------------------------------------------------------- 3: 12-bit data in mono16

SRGB_TOML = SMALL_TOML.replace("per_target = 3", "per_target = 6") + '[optics]\nresponse = "srgb"\n'


def _grey_edit(convert):
    def edit(topic: str, msg: dict):
        if topic != "/camera/image_raw/compressed":
            return msg
        px, enc = convert(png_grey(msg))
        return raw_image(msg, px, enc)

    return edit


def test_mono16_holding_12_bit_data_is_as_accurate_as_mono8(tmp_path, capsys):
    """An sRGB camera's 12-bit samples in mono16: same shape error as the 8-bit images."""
    from pipeline.accuracy.evaluate import judge_run

    rec, truth = simulated(tmp_path, seed=1, toml=SRGB_TOML)
    shape = {}
    for name, conv in {
        "mono8": lambda g: (g, "mono8"),
        "mono16_12": lambda g: (
            np.rint(g.astype(float) * (4095 / 255)).astype(np.uint16),
            "mono16",
        ),
    }.items():
        variant = rewrite(rec, tmp_path / f"{name}.mcap", _grey_edit(conv))
        out = tmp_path / name
        code, err = _run(variant, out, capsys, "--model", "full", "--until", "crossval")
        assert code == 0, err
        written_files_parse(out)
        shape[name] = judge_run(out, truth, 300, 1)["after"]["shape_rms_m"]
    assert shape["mono16_12"] <= 1.1 * shape["mono8"], shape
    info = json.loads((tmp_path / "mono16_12" / "recording.json").read_text())
    assert info["inferred"]["bit_depth"].startswith("12 "), info["inferred"]
    assert (
        "bit_depth"
        not in json.loads((tmp_path / "mono8" / "recording.json").read_text())["inferred"]
    )


# --------------------------------------------------------------- 4: XCDR2, NaN joint positions


def test_xcdr2_messages_read_as_their_cdr_twin(sim, tmp_path, capsys):
    """Every message in plain XCDR2 (8-byte values aligned to 4): the same calibration."""
    rec, _ = sim

    def frame(topic: str, msg: dict) -> dict:  # a driver that stamps its frame: 4 bytes
        if topic == "/joint_states":  # more before the positions, not a multiple of 8
            msg["header"]["frame_id"] = "base"
        return msg

    outs = {}
    for name, raw in {"cdr": None, "xcdr2": lambda t, m: xcdr2(t, m)}.items():
        variant = rewrite(rec, tmp_path / f"{name}.mcap", frame, raw=raw)
        outs[name] = tmp_path / name
        code, err = _run(variant, outs[name], capsys)
        assert code == 0, err
        written_files_parse(outs[name])
    a, b = (ET.tostring(ET.fromstring((outs[k] / "calibrated.urdf").read_bytes())) for k in outs)
    assert a == b  # comments (the provenance: file names and hashes) left out
    for f in ("touchups.parquet", "parameters.parquet"):
        ta, tb = (pq.read_table(outs[k] / f) for k in outs)
        assert ta.equals(tb), f


@pytest.mark.parametrize("kind", ["delimited_xcdr2", "nan_joint"])
def test_unreadable_messages_are_one_line(sim, tmp_path, capsys, kind):
    rec, _ = sim
    if kind == "delimited_xcdr2":
        variant = rewrite(rec, tmp_path / "d.mcap", raw=lambda t, m: xcdr2(t, m, delimited=True))
        needles = ["D_CDR2_LE (0x0009)", "CDR2_LE"]
    else:
        n = [0]

        def nan(topic: str, msg: dict) -> dict:
            if topic == "/joint_states":
                n[0] += 1
                if n[0] == 8:
                    msg["position"] = [
                        np.nan if k == 1 else x for k, x in enumerate(msg["position"])
                    ]
            return msg

        variant = rewrite(rec, tmp_path / "nan.mcap", nan)
        needles = ["/joint_states message 7: non-finite position joint_2=nan"]
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys)
    _one_error(code, err, 2, str(variant), *needles)
    assert not out.exists() or not any(out.iterdir()), sorted(out.iterdir())


# --------------------------------------------------------------- 5: 5-megapixel images


def test_five_megapixel_images_are_read_binned(sim, tmp_path, capsys):
    """2560x2048 images of the same scene: detected on 8x8 block means, same calibration."""
    rec, truth = sim
    from pipeline.accuracy.evaluate import judge_run

    shape = {}
    for f in (1, 16):
        variant = upscaled(rec, tmp_path / f"x{f}.mcap", f)
        out = tmp_path / f"x{f}"
        code, err = _run(variant, out, capsys, "--until", "crossval")
        assert code == 0, err
        written_files_parse(out)
        shape[f] = judge_run(out, truth, 300, 1)["after"]["shape_rms_m"]
    assert shape[16] <= 1.1 * shape[1], shape
    info = json.loads((tmp_path / "x16" / "recording.json").read_text())
    assert info["image_width"] == 2560 and info["inferred"]["binning"].startswith("8 ("), info


def test_a_refusal_after_ingest_leaves_nothing_in_out(sim, tmp_path, capsys):
    """Images with no target (a lens cap): refused at the touch-up stage, after ingest
    wrote its artefacts; they are withdrawn, and what the folder held before stays."""
    rec, _ = sim

    def capped(topic: str, msg: dict) -> dict:
        if topic == "/camera/image_raw/compressed":
            g = png_grey(msg)
            msg["data"] = raw_png(np.full_like(g, 23))
        return msg

    variant = rewrite(rec, tmp_path / "capped.mcap", capped)
    fresh = tmp_path / "fresh"
    code, err = _run(variant, fresh, capsys)
    _one_error(code, err, 2, str(variant), "no two still captures")
    assert not fresh.exists(), sorted(fresh.rglob("*"))
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("the cell's notes")
    code, err = _run(variant, kept, capsys)
    _one_error(code, err, 2, str(variant))
    assert sorted(p.name for p in kept.rglob("*")) == ["notes.txt"]


def raw_png(g: np.ndarray) -> bytes:
    import cv2

    return cv2.imencode(".png", g)[1].tobytes()


# --------------------------------------------------------------- 6: unknown keys and labels


@pytest.mark.parametrize(
    "extra,needles",
    [
        (
            ["--distance", "0:9=0.5"],
            ["known distance 0:9=0.5: no target '9'", "(targets: ['0', '1', '2'])"],
        ),
        (
            ["--set", "polarty=light_on_dark"],
            ["'polarty' is not a touchup metadata key (did you mean 'polarity'?)", "'polarity'"],
        ),
        (["--set", "idnetify.model=full"], ["no stage 'idnetify'", "'identify'"]),
        (
            ["--set", "identify.modle=full"],
            ["unknown option(s) for IdentifyConfig: modle", "model"],
        ),
    ],
)
def test_unknown_keys_and_labels_are_refused_with_the_valid_ones(
    sim, tmp_path, capsys, extra, needles
):
    rec, _ = sim
    out = tmp_path / "run"
    code, err = _run(rec, out, capsys, *extra)
    _one_error(code, err, 2, *needles)
    assert not out.exists(), sorted(out.rglob("*"))


# --------------------------------------------------------------- 8: calibrate's --urdf and reruns

REPO = Path(__file__).resolve().parent.parent
SIM_CELL = f"sim:{REPO / 'datasets' / 'scenarios' / 'small.toml'}:1"


def _cell_plan(path: Path, n: int) -> Path:
    import pandas as pd

    from pipeline.sim.link import sim_cell, write_plan

    cell, _ = sim_cell(SIM_CELL)
    write_plan(cell, str(path))
    pd.read_parquet(path).iloc[:n].to_parquet(path)
    return path


def test_measure_and_calibrate_take_a_builtin_robot_name(tmp_path, capsys):
    plan = _cell_plan(tmp_path / "plan.parquet", 2)
    rec = tmp_path / "rec.mcap"
    argv = ["measure", "--robot", SIM_CELL, "--plan", str(plan), "--urdf", "lrmate"]
    code, err = run_cli([*argv, "--out", str(rec), "-q"], capsys)
    assert code == 0, err
    from pipeline.robots import builtin_urdf

    def urdf_of(topic: str, msg: dict) -> dict:
        if topic == "/robot_description":
            assert msg["data"] == builtin_urdf("lrmate")
        return msg

    rewrite(rec, tmp_path / "check.mcap", urdf_of)
    code, err = run_cli([*argv[:-1], "nosuchrobot", "--out", str(tmp_path / "r2.mcap")], capsys)
    _one_error(code, err, 2, "'nosuchrobot': neither built in (lrmate, ur5e, iiwa7)")


def test_calibrate_refuses_to_reuse_another_plan_or_recording(tmp_path, capsys):
    out = tmp_path / "cal"
    out.mkdir()
    targets = tmp_path / "targets.csv"
    targets.write_text("target_id,x,y,z,nx,ny,nz\n0,0.5,0,0,0,0,1\n")
    old = _cell_plan(out / "plan.parquet", 2)
    (out / "plan.request.json").write_text(json.dumps({"poses": 24}))
    before = old.read_bytes()
    argv = ["calibrate", "--robot", SIM_CELL, "--urdf", "lrmate", "--out", str(out), "-q"]
    code, err = run_cli([*argv, "--targets", str(targets), "--poses", "12"], capsys)
    _one_error(code, err, 2, str(out), "made with --poses 24", "asks --poses 12")
    assert old.read_bytes() == before
    # a finished recording of one plan, calibrate asked to follow another
    code, err = run_cli(
        ["measure", "--robot", SIM_CELL, "--plan", str(old), "--out", str(out / "recording.mcap")],
        capsys,
    )
    assert code == 0, err
    other = _cell_plan(tmp_path / "other.parquet", 3)
    code, err = run_cli([*argv, "--plan", str(other)], capsys)
    _one_error(code, err, 2, "recording.mcap: was measured with another plan")
    assert not (out / "run").exists()


# --------------------------------------------------------------- 7: validate's guardrails


def test_validate_against_a_flipped_nominal_urdf_is_implausible(tmp_path, capsys):
    """The nominal URDF with joint_2's axis flipped: its 'before' is ~100 mm off, which made
    any calibration look thousands of times better; validate refuses it as identify does."""
    from pipeline.accuracy.evaluate import perturbed_chain, random_deviations, synthetic_touchups
    from pipeline.kinematics import load_chain
    from pipeline.robots import builtin_urdf

    nominal = builtin_urdf("lrmate")
    chain = load_chain(nominal, "base_link", "flange")
    true = perturbed_chain(chain, random_deviations(chain, np.random.default_rng(7)))
    tables = {}
    for name, seed in (("a", 1), ("b", 2)):
        tab, _ = synthetic_touchups(
            true, np.array([0.01, -0.02, 0.2]), 4, 10, np.random.default_rng(seed),
            noise_pin_m=2e-5, q_centre=[0.0, 0.3, -0.3, 0.0, -0.8, 0.0], spread_rad=0.9,
            centre_spread_rad=0.9,
        )  # fmt: skip
        tables[name] = tmp_path / f"{name}.csv"
        tab.to_csv(tables[name], index=False)
    (tmp_path / "nominal.urdf").write_text(nominal)
    i = nominal.index('<joint name="joint_2"')
    j = nominal.index("<axis", i)
    k = nominal.index("/>", j)
    flipped = nominal[:j] + '<axis xyz="0 -1 0"' + nominal[k:]
    assert flipped != nominal and '<axis xyz="0 1 0"' in nominal[i:k]
    (tmp_path / "flipped.urdf").write_text(flipped)
    code, err = run_cli(
        ["identify", str(tables["a"]), "--urdf", str(tmp_path / "nominal.urdf"), "--out",
         str(tmp_path / "cal"), "--flange-link", "flange", "--model", "full", "--no-crossval",
         "--no-report"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    argv = ["validate", str(tmp_path / "cal" / "calibrated.urdf"), str(tables["b"])]
    code, err = run_cli([*argv, "--urdf", str(tmp_path / "nominal.urdf")], capsys)
    assert code == 0, err  # the right nominal robot: plausible, improved
    out = tmp_path / "check"
    code, err = run_cli(
        [*argv, "--urdf", str(tmp_path / "flipped.urdf"), "--out", str(out)], capsys
    )
    _one_error(code, err, 3, "implausible input: the nominal robot fits these touch-ups to")
    assert "improved" not in err[0] and not (out / "validate.json").exists()
    code, err = run_cli(
        [
            *argv,
            "--urdf",
            str(tmp_path / "flipped.urdf"),
            "--out",
            str(out),
            "--accept-implausible",
        ],
        capsys,
    )
    assert (
        "the nominal robot fits"
        in json.loads((out / "validate.json").read_text())["implausible"][0]
    )


# --------------------------------------------------------------- 9: found means trustworthy


def test_a_found_detection_on_the_real_dot_photos_is_where_a_dot_is():
    """Real photos (datasets/real/dots): each whole photo (the board at the border, clipped
    surroundings), crops centred on a dot and crops that cut it at their left edge. Flagged fits put centres up
    to 364 px from any dot; none of them may be ``found``."""
    import importlib.util

    from pipeline.stages.detect.detector import detect_target

    spec = importlib.util.spec_from_file_location(
        "bench_real_images", REPO / "benchmarks" / "bench_real_images.py"
    )
    assert spec is not None and spec.loader is not None
    B = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(B)
    n_flagged = n_found = 0
    for _, g in B.photos()[:6]:
        c, s = B.opencv_blobs(g)
        crops = [(g, 0, 0, None)]
        for j in range(0, 100, 7):
            u, v = c[j]
            h = int(2.5 * s[j])
            for cut in (2.5, 0.0, 0.3):  # centred; the dot's centre at, or 0.3 s inside, the edge
                u0, v0 = int(u - cut * s[j]), max(int(v) - h, 0)
                crop = g[v0 : int(v) + h, u0 : int(u) + h]
                crops.append((crop, u0, v0, (u - u0, v - v0, s[j])))
        for img, u0, v0, expected in crops:
            r = detect_target(img, B.VTCAL_CONFIG, expected)
            n_flagged += bool(r["reason"]) and np.isfinite(r["u"])
            if r["found"]:
                n_found += 1
                assert r["quality_ok"] and not r["reason"], r
                miss = np.hypot(c[:, 0] - (r["u"] + u0), c[:, 1] - (r["v"] + v0)).min()
                assert miss < 1.0, (miss, r)
    assert n_flagged > 20 and n_found > 20, (n_flagged, n_found)


# --------------------------------------------------------------- 10: target_order names


def test_known_distances_by_the_names_of_target_order(sim, tmp_path, capsys):
    """The cell names its targets (``target_order``, first-touch order) and its bar by them:
    the same calibration as with first-touch labels; a name not in the list is refused."""
    rec, truth = sim
    first = truth["metadata"]["known_distances"]  # "0:2=0.589035" (first-touch labels)
    a, rest = first.split(":")
    b, metres = rest.split("=")
    outs = {}
    for name, order, names in [
        ("labels", None, None),
        ("words", "bar_left,plate,bar_right", ("bar_left", "plate", "bar_right")),
        ("ids", "7,3,5", ("7", "3", "5")),  # the cell's own ids, visited in another order
    ]:

        def md(m: dict[str, str], order=order, names=names) -> dict[str, str]:
            m = dict(m)
            if order is not None:
                m["target_order"] = order
                m["known_distances"] = f"{names[int(a)]}:{names[int(b)]}={metres}"
            return m

        variant = rewrite(rec, tmp_path / f"{name}.mcap", metadata=md)
        outs[name] = tmp_path / name
        code, err = _run(variant, outs[name], capsys, "--until", "identify")
        assert code == 0, err
        written_files_parse(outs[name])
    ref = pq.read_table(outs["labels"] / "parameters.parquet")
    for name in ("words", "ids"):
        assert pq.read_table(outs[name] / "parameters.parquet").equals(ref), name
    code, err = _run(
        tmp_path / "words.mcap", tmp_path / "bad", capsys, "--distance", "bar_left:bar_rihgt=0.5"
    )
    _one_error(
        code, err, 2, "no target 'bar_rihgt' in target_order ['bar_left', 'plate', 'bar_right']"
    )
    # a name without target_order: not a target of the run (was an internal error)
    code, err = _run(rec, tmp_path / "bad2", capsys, "--distance", "a:b=0.5")
    _one_error(code, err, 2, "known distance a:b=0.5: no target 'a'", "(targets: ['0', '1', '2'])")


# --------------------------------------------------------------- containers and encodings


def _image_msg(msg: dict, grey: np.ndarray, encoding: str) -> tuple[str, str, dict]:
    """``sensor_msgs/Image`` of one grey image in ``encoding`` as a driver writes it."""
    big = encoding.endswith("_be")
    enc = encoding.removesuffix("_be")
    g16 = grey.astype(np.uint16) * 257
    px = {
        "mono8": grey,
        "8UC1": grey,
        "mono16": g16,
        "16UC1": g16,
        "rgb8": np.dstack([grey] * 3),
        "bgr8": np.dstack([grey] * 3),
        "rgba8": np.dstack([grey] * 3 + [np.full_like(grey, 255)]),
        "bgra8": np.dstack([grey] * 3 + [np.full_like(grey, 255)]),
    }[enc]
    data = px.astype(">u2" if big else px.dtype.newbyteorder("<")).tobytes()
    out = {
        "header": msg["header"],
        "height": int(grey.shape[0]),
        "width": int(grey.shape[1]),
        "encoding": enc,
        "is_bigendian": int(big),
        "step": len(data) // grey.shape[0],
        "data": data,
    }
    return "/camera/image_raw", "sensor_msgs/msg/Image", out


def _encoded(encoding: str):
    import cv2

    def edit(topic: str, msg: dict):
        if topic != "/camera/image_raw/compressed":
            return msg
        grey = png_grey(msg)
        if encoding == "jpeg":
            msg["format"] = "jpeg"
            msg["data"] = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, 98])[1].tobytes()
            return msg
        return _image_msg(msg, grey, encoding)

    return edit


CONTAINERS = {
    "unchunked": {"use_chunking": False},
    "chunks_none_1k": {"compression": CompressionType.NONE, "chunk_size": 1024},
    "chunks_lz4": {"compression": CompressionType.LZ4},
    "chunks_zstd_4m": {"compression": CompressionType.ZSTD, "chunk_size": 1 << 22},
    "no_index_no_summary": {
        "index_types": IndexType.NONE,
        "use_statistics": False,
        "use_summary_offsets": False,
        "repeat_channels": False,
        "repeat_schemas": False,
    },
    "no_crcs": {"enable_crcs": False},
    "data_crcs": {"enable_data_crcs": True},
}
ENCODINGS = ["mono8", "8UC1", "mono16", "mono16_be", "16UC1", "rgb8", "bgr8", "rgba8", "bgra8"]


@pytest.fixture(scope="module")
def reference(sim, tmp_path_factory) -> float:
    from pipeline.accuracy.evaluate import judge_run
    from pipeline.run.orchestrator import RunConfig, run_pipeline

    rec, truth = sim
    out = tmp_path_factory.mktemp("ref") / "run"
    run_pipeline(rec, out, RunConfig(report=False), until="crossval")
    return judge_run(out, truth, 300, 1)["after"]["shape_rms_m"]


@pytest.mark.parametrize(
    "name,how",
    [*(("container", c) for c in CONTAINERS), *(("encoding", e) for e in [*ENCODINGS, "jpeg"])],
)
def test_every_container_option_and_encoding_reads_as_the_reference(
    sim, reference, tmp_path, capsys, name, how
):
    """MCAP written in each container option the spec allows, images in each encoding the
    spec's types allow: exit 0 within 1.1x of the reference's shape error, every file parses."""
    from pipeline.accuracy.evaluate import judge_run

    rec, truth = sim
    dst = tmp_path / "v.mcap"
    if name == "container":
        variant = rewrite(rec, dst, writer=CONTAINERS[how])
    else:
        variant = rewrite(rec, dst, _encoded(how))
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys, "--until", "crossval")
    assert code == 0 and not err, err  # every one of these is read, without a warning
    written_files_parse(out)
    assert judge_run(out, truth, 300, 1)["after"]["shape_rms_m"] <= 1.1 * reference


# --------------------------------------------------------------- inferred polarity


def test_light_targets_without_a_touchup_record_are_said_light_on_dark(tmp_path, capsys):
    """Automatic detection reads each image's polarity; recording.json says the majority
    (it said dark_on_light, the default, whatever the targets were)."""
    toml = SMALL_TOML.replace("count = 3", 'count = 3\npolarity = "light_on_dark"')
    rec, _ = simulated(tmp_path, seed=1, toml=toml)
    variant = rewrite(rec, tmp_path / "bare.mcap", metadata=lambda m: {}, drop_empty=True)
    out = tmp_path / "run"
    code, err = _run(variant, out, capsys, "--until", "touchups")
    assert code == 0, err
    info = json.loads((out / "recording.json").read_text())
    assert info["metadata"]["polarity"] == "light_on_dark"
    assert info["inferred"]["polarity"].startswith("light_on_dark (automatic per image: "), info


def test_target_ids_survive_a_plan_that_visits_them_out_of_order(tmp_path, capsys):
    """The plan visits targets 2, 0, 1; measure writes target_order 2,0,1, and a bar named by
    the targets file's ids (0:2) is the same pair as first-touch labels 1:0 would be."""
    import pandas as pd

    from pipeline.sim.link import sim_cell

    cell, _ = sim_cell(SIM_CELL)
    centre = {t.id: t.centre for t in cell.sess.cell.targets}
    d02 = float(np.linalg.norm(centre[0] - centre[2]))
    plan = _cell_plan(tmp_path / "plan.parquet", 6)
    df = pd.read_parquet(plan)
    df = pd.concat([df[df.target_id == 2], df[df.target_id != 2]]).reset_index(drop=True)
    df.to_parquet(plan)
    rec = tmp_path / "rec.mcap"
    code, err = run_cli(
        ["measure", "--robot", SIM_CELL, "--plan", str(plan), "--out", str(rec), "-q",
         "--set", f"known_distances=0:2={d02!r}"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    seen = {}

    def by_labels(m: dict[str, str]) -> dict[str, str]:
        seen.update(m)
        return {**{k: v for k, v in m.items() if k != "target_order"},
                "known_distances": f"1:0={d02!r}"}  # fmt: skip

    twin = rewrite(rec, tmp_path / "labels.mcap", metadata=by_labels)
    assert seen["target_order"] == "2,0,1" and seen["known_distances"] == f"0:2={d02!r}"
    outs = {}
    for name, r in (("names", rec), ("labels", twin)):
        outs[name] = tmp_path / name
        code, err = _run(r, outs[name], capsys, "--until", "identify", "--model", "offsets")
        assert code in (0,), err
    a, b = (pq.read_table(outs[k] / "parameters.parquet") for k in ("names", "labels"))
    assert a.equals(b)
    summary = json.loads((outs["names"] / "identify.json").read_text())
    assert summary.get("distances_dropped", []) == [], summary.get("distances_dropped")


# ------------------------------------------------------------ level-of-detail images

LOD_TOML = (
    SMALL_TOML.replace("width = 160", "width = 320")
    .replace("height = 128", "height = 256")
    .replace("f_px = 300.0", "f_px = 600.0")
)


def test_level_of_detail_images_are_read_in_the_sensors_pixels(tmp_path, capsys):
    """Every other capture sent at half resolution (area-averaged, as a recorder's
    level-of-detail stream): each is detected at its own size and mapped to the full
    size's pixels (L1), so its centre and long axis agree with the full-resolution
    recording's within a tenth of a pixel, and the calibration is as good (1.2x)."""
    import cv2
    import pandas as pd

    from pipeline.accuracy.evaluate import judge_run

    rec, truth = simulated(tmp_path, seed=2, toml=LOD_TOML)
    seen = [0]

    def half(topic: str, msg: dict):
        if "image" not in topic:
            return msg
        grey = png_grey(msg)
        seen[0] += 1
        if seen[0] % 2 == 0:
            grey = cv2.resize(
                grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA
            )
        return raw_image(msg, grey, "mono8")

    variant = rewrite(rec, tmp_path / "lod.mcap", half)
    runs = {}
    for name, r in (("full", rec), ("lod", variant)):
        out = tmp_path / name
        code, err = _run(r, out, capsys, "--until", "crossval")
        assert code == 0 and not err, err
        runs[name] = out
    full = pd.read_parquet(runs["full"] / "detections.parquet")
    lod = pd.read_parquet(runs["lod"] / "detections.parquet")
    both = full["found"] & lod["found"]
    halved = np.zeros(len(full), bool)
    halved[1::2] = True
    assert (both & halved).sum() > 20
    for col, tol in (("u", 0.1), ("v", 0.1), ("s", 0.1)):
        d = (lod[col] - full[col])[both & halved].abs()
        assert float(d.median()) < tol / 2 and float(d.max()) < 3 * tol, (col, d.describe())
    info = json.loads((runs["lod"] / "recording.json").read_text())
    assert (info["image_width"], info["image_height"]) == (320, 256)
    ref = judge_run(runs["full"], truth, 300, 1)["after"]["shape_rms_m"]
    assert judge_run(runs["lod"], truth, 300, 1)["after"]["shape_rms_m"] <= 1.2 * ref
