"""Ingest: streaming MCAP reading, joint interpolation, stillness, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.writer import CompressionType
from support.mcap_write import write_recording
from test_robustness_data import MS, NAMES, T0, URDF

from pipeline.errors import BadInput
from pipeline.io.artefacts import write_artefact
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.ingest.stage import IngestConfig, ingest_recording, load_image


def disc_image(u: float, v: float, r: float, w: int = 160, h: int = 128, dark: bool = True):
    """Area-coverage disc (8x8 supersampling), light plate 200 / target 40."""
    n = 8
    off = (np.arange(n) + 0.5) / n - 0.5
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    cov = np.zeros((h, w))
    for dy in off:
        for dx in off:
            cov += np.hypot(uu + dx - u, vv + dy - v) <= r
    cov /= n * n
    lo, hi = (40.0, 200.0) if dark else (200.0, 40.0)
    img = hi * (1 - cov) + lo * cov
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def q_of_t(t_ns: int) -> np.ndarray:
    """Joint trajectory: still until 1 s, moving 1-2 s, still afterwards."""
    s = (t_ns - T0) / 1e9
    x = np.clip(s - 1.0, 0.0, 1.0)
    return np.array([0.1 + 0.2 * x, -0.3 + 0.1 * x])


def make(path, encoding="mono8", short_names=False, n_img=5, **kw):
    joints = kw.pop("joints", [(T0 + k * 10 * MS, q_of_t(T0 + k * 10 * MS)) for k in range(400)])
    stamps = [T0 + int(s * 1e9) for s in (0.3, 0.6, 1.5, 2.5, 3.2)][:n_img]
    imgs = kw.pop("images", [(t, disc_image(70.3 + i, 60.7, 12.0)) for i, t in enumerate(stamps)])
    write_recording(
        path,
        urdf=kw.pop("urdf", URDF),
        joint_names=kw.pop("joint_names", NAMES),
        joints=joints,
        images=imgs,
        encoding=encoding,
        short_names=short_names,
        metadata=kw.pop("metadata", {"polarity": "dark_on_light", "designated_size_px": "24"}),
        **kw,
    )
    return stamps


@pytest.mark.parametrize(
    "encoding,short",
    [
        ("mono8", False),
        ("mono8", True),
        ("mono16", False),
        ("rgb8", True),
        ("bgr8", False),
        ("png", True),
        ("jpeg", False),
    ],
)
def test_roundtrip_encodings(tmp_path, encoding, short):
    p = tmp_path / "rec.mcap"
    stamps = make(p, encoding=encoding, short_names=short)
    frames, dets, info = ingest_recording(p, IngestConfig(), DetectConfig())
    assert info.n_images == 5 and not info.truncated
    assert info.joint_names == NAMES and info.base_link == "base_link"
    assert info.flange_link == "flange" and "flange_link" in info.inferred
    assert list(frames["stamp_ns"]) == stamps
    # joint vector interpolated at the stamps (the trajectory is piecewise linear)
    for t, row in zip(stamps, frames.itertuples(), strict=True):
        assert np.allclose([row.j1, row.j2], q_of_t(t), atol=1e-9)
    # the capture at 1.5 s is taken while moving, the others are still
    assert list(frames["moving"]) == [False, False, True, False, False]
    assert not frames["joint_gap"].any()
    tol = 0.05 if encoding == "jpeg" else 0.02
    assert dets["found"].all()
    assert np.allclose(dets["u"], 70.3 + np.arange(5), atol=tol)
    assert np.allclose(dets["v"], 60.7, atol=tol)
    assert np.allclose(dets["s"], 24.0, atol=2 * tol)
    write_artefact(tmp_path / "frames.parquet", frames, "frames", stage="ingest")
    write_artefact(tmp_path / "det.parquet", dets, "detections", stage="ingest")
    img = load_image(p, info.image_topic, 3)
    assert img.shape == (128, 160)


@pytest.mark.parametrize(
    "fox,encoding", [("json", "mono8"), ("json", "png"), ("protobuf", "mono8"), ("protobuf", "png")]
)
def test_foxglove_images(tmp_path, fox, encoding):
    if fox == "protobuf":
        pytest.importorskip("foxglove_schemas_protobuf")
    p = tmp_path / "fox.mcap"
    stamps = make(p, encoding=encoding, foxglove=fox)
    frames, dets, info = ingest_recording(p, IngestConfig(), DetectConfig())
    assert info.n_images == 5 and list(frames["stamp_ns"]) == stamps
    assert np.allclose(dets["u"], 70.3 + np.arange(5), atol=0.02)


def test_progress_and_metadata_overrides(tmp_path):
    p = tmp_path / "rec.mcap"
    make(p)
    calls = []
    cfg = IngestConfig(overrides={"designated_size_px": "30"})
    _, _, info = ingest_recording(
        p, cfg, DetectConfig(), progress=lambda a, b: calls.append((a, b))
    )
    assert calls and calls[-1] == (5, 5)
    assert info.metadata["designated_size_px"] == "30"
    assert info.metadata["polarity"] == "dark_on_light"
    assert "designated_u" in info.inferred  # not in the file: image centre


def test_joint_gap_and_truncation(tmp_path):
    p = tmp_path / "rec.mcap"
    joints = [(T0 + k * 10 * MS, q_of_t(T0 + k * 10 * MS)) for k in range(400)]
    joints = [j for j in joints if not (T0 + 2400 * MS < j[0] < T0 + 2700 * MS)]
    make(p, joints=joints, chunk_size=8000, compression=CompressionType.NONE)
    frames, _, _ = ingest_recording(p, IngestConfig(), DetectConfig())
    assert list(frames["joint_gap"]) == [False, False, False, True, False]
    data = p.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    frames2, dets2, info2 = ingest_recording(cut, IngestConfig(), DetectConfig())
    assert info2.truncated and 0 < info2.n_images < 5
    assert any("truncated" in w for w in info2.warnings)
    assert dets2["found"].all()


@pytest.mark.parametrize(
    "kind,needle",
    [
        ("no_images", "no image messages"),
        ("no_joints", "no joint states"),
        ("unknown_encoding", "unknown image encoding 'yuv422'"),
        ("wrong_names", "does not have"),
        ("nan", "non-finite"),
        ("no_urdf", "no URDF"),
    ],
)
def test_bad_input_one_line(tmp_path, kind, needle):
    p = tmp_path / f"{kind}.mcap"
    kw: dict = {}
    if kind == "no_images":
        kw["images"] = []
    elif kind == "no_joints":
        kw["joints"] = []
    elif kind == "unknown_encoding":
        kw["encoding"] = "yuv422"
    elif kind == "wrong_names":
        kw["joint_names"] = ["shoulder", "elbow"]
    elif kind == "nan":
        kw["joints"] = [
            (T0 + k * 10 * MS, np.array([0.1, np.nan if k == 7 else 0.2])) for k in range(50)
        ]
    elif kind == "no_urdf":
        kw["urdf"] = None
    make(p, **kw)
    with pytest.raises(BadInput) as exc:
        ingest_recording(p, IngestConfig(), DetectConfig())
    msg = str(exc.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


def test_not_an_mcap(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not an mcap")
    with pytest.raises(BadInput, match="not an MCAP"):
        ingest_recording(p, IngestConfig(), DetectConfig())


def test_conformance_sample(conformance_sample, conformance_truth):
    frames, dets, info = ingest_recording(conformance_sample, IngestConfig(), DetectConfig())
    truth = conformance_truth
    assert info.n_images == truth["counts"]["images"]
    assert info.n_joint_states == truth["counts"]["joint_states"]
    assert list(frames["stamp_ns"]) == [im["stamp_ns"] for im in truth["images"]]
    # captures while moving are flagged, still ones are not
    moving = np.array([im["moving"] for im in truth["images"]])
    assert np.array_equal(frames["moving"].to_numpy(), moving)
    # joints at the stamp match the true (noise-free) encoder angles to encoder noise
    q_true = np.array([im["q_true"] for im in truth["images"]])
    still = ~moving
    err = np.abs(frames[info.joint_names].to_numpy()[still] - q_true[still])
    assert err.max() < 2e-5
    # the occluded (lost) capture is not found; clean captures match the true circle centre
    lost = [im["index"] for im in truth["images"] if im["occluded"]]
    assert not dets.loc[lost, "found"].any()


def test_cli_run_bad_input_exit_code(tmp_path, capsys):
    """`vtcal run` on a recording whose joints do not match its URDF: one line, exit 2."""
    from pipeline.cli import main

    p = tmp_path / "bad.mcap"
    make(p, joint_names=["shoulder", "elbow"])
    with pytest.raises(SystemExit) as exc:
        main(["run", str(p), "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shoulder" in err[0] and str(p) in err[0]


@pytest.mark.parametrize("compression", [CompressionType.LZ4, CompressionType.NONE])
def test_chunk_compressions(tmp_path, compression):
    p = tmp_path / "rec.mcap"
    make(p, compression=compression, chunk_size=50_000)
    frames, dets, info = ingest_recording(p, IngestConfig(), DetectConfig())
    assert info.n_images == 5 and not info.truncated and dets["found"].all()
