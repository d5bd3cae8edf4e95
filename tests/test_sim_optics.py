"""Real-camera image formation in the simulator (scenario ``[optics]``, issue 14).

Each knob changes the images the way its physics says, is seeded and recorded in
the truth, and the recordings it writes (colour, JPEG) follow the spec.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from pipeline.errors import BadInput
from pipeline.sim.optics import Response, Sensor, form_image, srgb_encode
from pipeline.sim.scenario import OpticsCfg, scenario_from_dict
from pipeline.sim.simulator import write_recording
from pipeline.sim.target_geometry import PrintShape, projected_ellipse

ROOT = Path(__file__).resolve().parents[1]
CHECKER = Path("/work/shared/tools/check_recording.py")


def tiny(optics: dict[str, Any], per_target: int = 1, count: int = 1) -> Any:
    raw = tomllib.loads((ROOT / "datasets" / "scenarios" / "small.toml").read_text())
    raw["poses"]["per_target"] = per_target
    raw["targets"]["count"] = count
    raw["targets"]["bar"] = False
    raw["optics"] = optics
    return scenario_from_dict(raw, where="tiny", base_dir=str(ROOT))


def images(path: Path) -> list[tuple[str, Any]]:
    with path.open("rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        return [
            (c.topic, ros)
            for _, c, _, ros in r.iter_decoded_messages()
            if c.topic.startswith("/camera")
        ]


def test_defaults_are_off_and_unknown_values_are_refused() -> None:
    assert not OpticsCfg().any()
    assert OpticsCfg(response="srgb").sensor_active()
    assert OpticsCfg(out_of_round_um=10).print_active()
    for bad in (
        {"response": "log"},
        {"demosaic": "magic"},
        {"jpeg_quality": 101},
        {"noise_domain": "adc"},
    ):
        with pytest.raises(BadInput, match="optics"):
            tiny(bad)


def test_srgb_moves_the_halfway_grey_but_not_the_halfway_irradiance() -> None:
    """A blurred step through the sRGB curve: its halfway *grey* point is off the edge."""
    x = np.linspace(-4, 4, 801)
    E = 40 + 160 * 0.5 * (1 + np.tanh(x / 0.8))  # linear grey, edge at x = 0
    sensor = Sensor(response=Response("srgb"), noise_sigma=0.0, vignetting=0.0)
    img, grey = form_image(
        np.tile(E, (2, 1)),
        sensor,
        principal_point=(0.0, 0.0),
        rng_noise=np.random.default_rng(0),
        rng_optics=np.random.default_rng(0),
    )
    g = grey[0].astype(float)
    half = 0.5 * (g[0] + g[-1])
    x_grey = x[np.argmin(np.abs(g - half))]
    lin = srgb_encode(np.array([40, 120, 200]) / 255.0) * 255
    assert abs(lin[1] - 0.5 * (lin[0] + lin[2])) > 10  # the curve is far from linear there
    assert -0.4 < x_grey < -0.1  # the halfway grey lies ~0.2 px inside the dark side


def test_an_out_of_round_print_changes_the_long_axis_with_the_view() -> None:
    from pipeline.sim.camera import CameraModel

    cam = CameraModel(width=640, height=512, fx=900.0, fy=900.0, cx=319.5, cy=255.5)
    shape = PrintShape(radius_m=0.005, ellipticity=1e-3, orientation_rad=0.3)

    def T(roll: float, tilt: float) -> np.ndarray:
        from pipeline.kinematics.se3 import matrix_from_axis_angle

        M = np.eye(4)
        # tilted about the camera's x, the plate then turned about its own normal
        M[:3, :3] = matrix_from_axis_angle(
            np.array([1.0, 0.0, 0.0]), tilt
        ) @ matrix_from_axis_angle(np.array([0.0, 0.0, 1.0]), roll)
        M[:3, 3] = [0.0, 0.0, 0.17]
        return M

    circle = [projected_ellipse(cam, T(r, 0.5), 0.010)[2] for r in (0.0, 0.8, 1.6)]
    printed = [projected_ellipse(cam, T(r, 0.5), 0.010, shape=shape)[2] for r in (0.0, 0.8, 1.6)]
    assert np.ptp(circle) < 1e-6
    # a 1e-3 ellipticity swings the long axis by ~ +-1e-3 of ~53 px with the roll
    assert 0.05 < np.ptp(printed) < 0.2


@pytest.fixture(scope="module")
def colour_jpeg(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    sc = tiny(
        {
            "response": "curve",
            "bayer": True,
            "jpeg_quality": 90,
            "shot_noise": True,
            "prnu_sigma": 0.01,
            "illumination": 0.2,
            "out_of_round_um": 20.0,
            "defocus_px": 1.0,
            "vibration_m": 2e-5,
        }
    )
    out = tmp_path_factory.mktemp("optics") / "colour.mcap"
    return out, write_recording(sc, 5, out)


def test_every_knob_and_draw_is_in_the_truth(colour_jpeg: tuple[Path, dict[str, Any]]) -> None:
    _, truth = colour_jpeg
    op = truth["optics"]
    assert op["config"]["bayer"] is True and op["config"]["jpeg_quality"] == 90
    assert op["response"]["kind"] == "curve" and len(op["response"]["table"]) == 256
    assert set(op["response"]["params"]) == {"gamma", "contrast", "pivot", "weight"}
    t = np.array(op["response"]["table"])
    assert t[0] == 0 and abs(t[-1] - 255) < 1e-6 and np.all(np.diff(t) > 0)  # monotone
    pr = op["prints"]["0"]
    assert abs(pr["semi_axes_m"][0] - pr["semi_axes_m"][1] - 10e-6) < 1e-9  # 20 um diameters
    assert op["lights"]["0"]["gradient_per_m"] != [0.0, 0.0]
    assert op["defocus"]["k_px_m"] > 0
    assert truth["image_encoding"] == "jpeg"


def test_colour_jpeg_recording_follows_the_spec(colour_jpeg: tuple[Path, dict[str, Any]]) -> None:
    path, _ = colour_jpeg
    ims = images(path)
    assert ims and all(t == "/camera/image_raw/compressed" for t, _ in ims)
    assert all(m.format == "jpeg" for _, m in ims)
    img = cv2.imdecode(np.frombuffer(bytes(ims[0][1].data), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.ndim == 3 and img.shape[2] == 3  # demosaiced colour
    if CHECKER.exists():
        r = subprocess.run(
            [sys.executable, str(CHECKER), str(path)], capture_output=True, text=True
        )
        assert r.returncode == 0, r.stdout + r.stderr


def test_bayer_raw_is_bgr8_and_the_pipeline_reads_it(tmp_path: Path) -> None:
    sc = tiny({"bayer": True, "response": "srgb"})
    sc = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, image="raw"))
    out = tmp_path / "bgr.mcap"
    truth = write_recording(sc, 2, out)
    ims = images(out)
    assert {m.encoding for _, m in ims} == {"bgr8"}
    assert truth["image_encoding"] == "bgr8"
    from pipeline.run.orchestrator import RunConfig, run_pipeline

    run_pipeline(out, tmp_path / "run", RunConfig(report=False), until="touchups")
    cam = json.loads((tmp_path / "run" / "recording.json").read_text())["camera"]
    assert cam["response"] == "srgb"  # found from the edges of the colour images


def test_same_seed_same_bytes_and_knobs_leave_other_draws_alone(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.mcap", tmp_path / "b.mcap", tmp_path / "c.mcap"
    ta = write_recording(tiny({"response": "srgb", "out_of_round_um": 15.0}), 4, a)
    write_recording(tiny({"response": "srgb", "out_of_round_um": 15.0}), 4, b)
    tc = write_recording(
        tiny({"response": "srgb", "out_of_round_um": 15.0, "shot_noise": True}), 4, c
    )
    assert a.read_bytes() == b.read_bytes()
    # shot noise draws from its own stream: the cell, the prints and the plan are the same
    assert ta["optics"]["prints"] == tc["optics"]["prints"]
    assert ta["true_urdf"] == tc["true_urdf"]
    assert [t["centre"] for t in ta["targets"]] == [t["centre"] for t in tc["targets"]]


def test_vibration_moves_the_image_but_not_the_encoders(tmp_path: Path) -> None:
    still = write_recording(tiny({}), 3, tmp_path / "s.mcap")
    shaky = write_recording(
        tiny({"vibration_m": 1e-4, "vibration_hz": 5.0}), 3, tmp_path / "v.mcap"
    )
    first = [i for i in still["images"] if i["kind"] == "probe"][0]
    first_v = [i for i in shaky["images"] if i["kind"] == "probe"][0]
    assert first["q_true"] == first_v["q_true"]  # same joints ...
    d = np.subtract(first["true_centre_px"], first_v["true_centre_px"])
    assert np.linalg.norm(d) > 0.05  # ... another image position


def _linear_noise(domain: str, kind: str, level: float) -> float:
    """Std of the signal a flat field at ``level`` (fraction of full scale) decodes to."""
    resp = Response(kind=kind)
    sensor = Sensor(response=resp, noise_sigma=2.0, noise_domain=domain, vignetting=0.0)
    L = np.full((160, 160), 255.0 * level)
    img, _ = form_image(
        L,
        sensor,
        principal_point=(80.0, 80.0),
        rng_noise=np.random.default_rng(5),
        rng_optics=np.random.default_rng(6),
    )
    grid = np.linspace(0.0, 1.0, 20001)
    decoded = np.interp(img.astype(float) / 255.0, resp.encode(grid), grid)
    return float(decoded.std() * 255.0)


def test_the_cameras_noise_enters_before_its_response_curve() -> None:
    """``noise_domain = "sensor"`` (the default): 2 grey levels of noise on the signal at
    any brightness, as a sensor's read noise; ``output``: the encoded image's noise, which
    the sRGB curve's slope shrinks on the dark side and stretches on the bright side."""
    assert Sensor().noise_domain == "sensor" and OpticsCfg().noise_domain == "sensor"
    dark, bright = (_linear_noise("sensor", "srgb", lv) for lv in (0.15, 0.8))
    assert 1.8 < dark < 2.2 and 1.8 < bright < 2.2, (dark, bright)
    dark_o, bright_o = (_linear_noise("output", "srgb", lv) for lv in (0.15, 0.8))
    assert bright_o / dark_o > 2.0, (dark_o, bright_o)  # slope ratio f'(0.15) / f'(0.8) ~ 2.9


def test_a_linear_camera_gives_the_same_image_in_either_noise_domain() -> None:
    L = np.random.default_rng(1).uniform(20.0, 240.0, (64, 80))
    imgs = []
    for domain in ("sensor", "output"):
        sensor = Sensor(noise_sigma=2.0, noise_domain=domain)
        img, _ = form_image(
            L,
            sensor,
            principal_point=(40.0, 32.0),
            rng_noise=np.random.default_rng(2),
            rng_optics=np.random.default_rng(3),
        )
        imgs.append(img)
    assert np.array_equal(imgs[0], imgs[1])
