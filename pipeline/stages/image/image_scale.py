"""Images at another resolution than the recording's sensor (level-of-detail images).

A recorder may send some captures scaled down (a loop's intermediate captures
at half or quarter resolution, the final ones at full), each still a plain
``sensor_msgs/Image`` of its own size. A detection is in the pixels of the image
it was made on, whereas the designated values, the image Jacobian and every
touch-up are in the sensor's. Each image is detected at its own size (its edge
is as sharp there as the detector needs) and its detection mapped to the
recording's reference grid, the largest image size seen, with the binning map
(:func:`pipeline.stages.image.binning.unbin`) of factor ``f = W_ref / W``::

    u_ref = f u + (f - 1) / 2,    v_ref = f v + (f - 1) / 2,    s_ref = f s       (L1)

(pixel ``j`` of the smaller image covers reference pixels ``j f .. j f + f - 1``).
An image whose two sides scale by different factors is not a scaled copy of the
sensor's (a crop, another camera): its detection is marked not found
(``image_size``), never mapped by a guess.
"""

from __future__ import annotations

from typing import Any

from pipeline.stages.image.binning import unbin

#: two sides' factors closer than this are one factor
SAME_FACTOR = 1e-3


def reference_shape(shapes: list[tuple[int, int]]) -> tuple[int, int]:
    """The recording's reference ``(H, W)``: the largest image (by area) among ``shapes``."""
    seen = [sh for sh in shapes if sh[0] > 0 and sh[1] > 0]
    return max(seen, key=lambda sh: (sh[0] * sh[1], sh)) if seen else (0, 0)


def to_reference(
    det: dict[str, Any], shape: tuple[int, int], ref: tuple[int, int]
) -> dict[str, Any]:
    """A detection on an image of ``shape`` (H, W) in the pixels of ``ref`` by (L1)."""
    if shape == ref or shape[0] <= 0 or not det.get("found", False):
        return det
    fh, fw = ref[0] / shape[0], ref[1] / shape[1]
    if abs(fh - fw) > SAME_FACTOR * max(fh, fw):
        out = dict(det)
        out["found"] = False
        out["quality_ok"] = False
        out["reason"] = f"image_size: {shape[1]}x{shape[0]} is no scaled {ref[1]}x{ref[0]}"
        return out
    return unbin(det, 0.5 * (fh + fw))
