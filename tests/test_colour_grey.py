"""Colour images to grey: the plain mean of the channels, not luma weights (issue 14).

Behind a Bayer mosaic each colour channel of a demosaiced image is interpolated
from other photosites; on a neutral target their edge errors differ by channel,
and the luma sum (ITU-R BT.601, what vtcal used before) keeps them. Rendered
discs behind an RGGB mosaic (bilinear demosaicing, shot noise, 2 grey levels of
noise) are detected from the mean as well as the same sensor without the
mosaic, and better than from luma weights.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.io.mcap import EncodedImage, colour_to_grey, image_to_gray
from pipeline.sim.optics import Sensor, form_image
from pipeline.stages.detect.detector import DetectConfig, detect_target

H, W = 200, 240


def _disc(cx: float, cy: float, r: float, ss: int = 8) -> np.ndarray:
    """Linear irradiance of a dark disc (40) on a light plate (200), pixel area, blur 0.7 px."""
    y, x = np.mgrid[0 : H * ss, 0 : W * ss]
    x = (x + 0.5) / ss - 0.5
    y = (y + 0.5) / ss - 0.5
    inside = ((x - cx) ** 2 + (y - cy) ** 2 <= r * r).astype(float)
    cover = inside.reshape(H, ss, W, ss).mean(axis=(1, 3))
    return cv2.GaussianBlur(200.0 - 160.0 * cover, (0, 0), 0.7)


def _errors(n: int = 30) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    out: dict[str, list[tuple[float, float, float]]] = {"luma": [], "mean": [], "mono": []}
    for i in range(n):
        cx, cy = 120 + rng.uniform(-2, 2), 100 + rng.uniform(-2, 2)
        r = 27 + rng.uniform(-0.5, 0.5)
        L = _disc(cx, cy, r)
        for bayer in (True, False):
            sensor = Sensor(bayer=bayer, noise_sigma=2.0, shot_noise=True)
            img, grey = form_image(
                L,
                sensor,
                principal_point=(W / 2, H / 2),
                rng_noise=np.random.default_rng(i),
                rng_optics=np.random.default_rng(100 + i),
            )
            greys = (
                {"luma": cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), "mean": colour_to_grey(img)}
                if bayer
                else {"mono": grey}
            )
            for key, g in greys.items():
                d = detect_target(g, DetectConfig(), None)
                out[key].append((d["u"] - cx, d["v"] - cy, d["s"] - 2 * r))
    return {k: np.array(v) for k, v in out.items()}


def test_mean_of_channels_detects_a_bayer_image_as_well_as_a_mono_one() -> None:
    e = _errors()
    centre = {k: float(np.sqrt(np.mean(v[:, :2] ** 2))) for k, v in e.items()}
    size_sd = {k: float(np.std(v[:, 2])) for k, v in e.items()}
    assert centre["mean"] < 1.25 * centre["mono"], centre
    assert size_sd["mean"] < 1.25 * size_sd["mono"], size_sd
    # the luma weights vtcal used before are measurably worse (the test tells them apart)
    assert centre["luma"] > 1.3 * centre["mean"], centre
    assert size_sd["luma"] > 1.2 * size_sd["mean"], size_sd


def test_decoded_colour_images_are_the_mean_of_their_channels() -> None:
    rng = np.random.default_rng(0)
    px = rng.integers(0, 256, (6, 5, 3)).astype(np.uint8)
    want = np.rint(px.astype(float).mean(axis=2)).astype(np.uint8)
    for enc, arr in (("bgr8", px), ("rgb8", px[:, :, ::-1])):
        img = EncodedImage(0, "raw", enc, 6, 5, 15, False, np.ascontiguousarray(arr).tobytes())
        np.testing.assert_array_equal(image_to_gray(img), want)
    alpha = np.concatenate([px, np.full((6, 5, 1), 7, np.uint8)], axis=2)
    img = EncodedImage(0, "raw", "bgra8", 6, 5, 20, False, alpha.tobytes())
    np.testing.assert_array_equal(image_to_gray(img), want)
    ok, png = cv2.imencode(".png", px)
    assert ok
    np.testing.assert_array_equal(
        image_to_gray(EncodedImage(0, "compressed", "png", data=png.tobytes())), want
    )
