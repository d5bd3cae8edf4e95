"""Field-recording variants against their reference: shape error ratio per variant.

For each seed: simulate a small LR Mate recording (160x128 PNG, 3 targets x 6
poses), rewrite it message by message as another recorder would
(``tests/support/field_variants.py``), run the pipeline on each variant
(``--model full``; the camera's response ``--response``, default sRGB) and judge the shipped ``calibrated.urdf`` against the
simulator's truth over 500 poses (``pipeline.accuracy.evaluate.judge_run``). Printed:
each variant's shape RMS and its ratio to the same images in ``mono8``
(PNG as simulated, and the same scene upscaled 16x to 2560x2048 PNG, are
there too).

    python benchmarks/bench_field_variants.py              # seeds 1-4, sRGB camera
    python benchmarks/bench_field_variants.py --seeds 1 2
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the test kit

from support.field_variants import png_grey, raw_image, rewrite, upscaled  # noqa: E402

from pipeline.accuracy.evaluate import judge_run  # noqa: E402
from pipeline.run.orchestrator import RunConfig, run_pipeline  # noqa: E402
from pipeline.sim.scenario import load_scenario  # noqa: E402
from pipeline.sim.simulator import simulate  # noqa: E402

TOML = """
name = "field_bench"
[robot]
name = "lrmate"
[camera]
width = 160
height = 128
f_px = 300.0
subsamples = 4
[targets]
count = 3
polarity = "{polarity}"
[poses]
per_target = 6
[optics]
response = "{response}"
"""


def _images(convert: Callable[[np.ndarray], tuple[np.ndarray, str]]) -> Any:
    def edit(topic: str, msg: dict[str, Any]) -> Any:
        if topic != "/camera/image_raw/compressed":
            return msg
        px, enc = convert(png_grey(msg))
        return raw_image(msg, px, enc)

    return edit


def _every_other_halved() -> Any:
    """Level-of-detail images: every other capture at half size (area means), mono8."""
    import cv2

    seen = [0]

    def convert(g: np.ndarray) -> tuple[np.ndarray, str]:
        seen[0] += 1
        if seen[0] % 2 == 0:
            g = cv2.resize(g, (g.shape[1] // 2, g.shape[0] // 2), interpolation=cv2.INTER_AREA)
        return g, "mono8"

    return _images(convert)


def to_12bit(g: np.ndarray) -> np.ndarray:
    """8-bit grey as a 12-bit sensor would give it (0-4095) in a uint16."""
    return np.rint(g.astype(np.float64) * (4095.0 / 255.0)).astype(np.uint16)


VARIANTS: dict[str, Any] = {
    "mono8": _images(lambda g: (g, "mono8")),
    "mono16 (16-bit)": _images(lambda g: (g.astype(np.uint16) * 257, "mono16")),
    "mono16 (12-bit data)": _images(lambda g: (to_12bit(g), "mono16")),
    "png (as simulated)": None,
    "png 5 MP (x16 upscaled)": 16,
    "level-of-detail (every other image at half size)": _every_other_halved(),
    "no designated/threshold": ("meta", lambda m: {
        k: v for k, v in m.items() if not k.startswith(("designated", "threshold"))
    }),
    "only the link names": ("meta", lambda m: {
        k: v for k, v in m.items() if k in ("base_link", "flange_link")
    }),
    "no touchup record": ("meta", None),
}  # fmt: skip


def _variant(rec: Path, dst: Path, how: Any) -> Path:
    if isinstance(how, int):
        return upscaled(rec, dst, how)
    if isinstance(how, tuple):
        keep = how[1]
        return rewrite(rec, dst, metadata=keep if keep else lambda m: {}, drop_empty=True)
    return rewrite(rec, dst, how)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--response", default="srgb", help="the simulated camera's response curve")
    ap.add_argument("--variants", nargs="+", default=None, help="names (prefixes) to run")
    ap.add_argument("--polarity", default="dark_on_light", help="the targets' polarity")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_field_"))
    scen = work / "s.toml"
    scen.write_text(TOML.replace("{response}", args.response).replace("{polarity}", args.polarity))
    chosen = {
        k: v
        for k, v in VARIANTS.items()
        if k == "mono8" or not args.variants or any(k.startswith(p) for p in args.variants)
    }
    table: dict[str, list[float]] = {k: [] for k in chosen}
    for seed in args.seeds:
        rec = work / f"sim_{seed}.mcap"
        truth = simulate(load_scenario(scen), seed=seed, out=rec)
        for name, edit in chosen.items():
            dst = work / f"{seed}_{len(table[name])}_{name[:6]}.mcap"
            var = _variant(rec, dst, edit)
            out = work / f"run_{seed}_{name.replace(' ', '_')}"
            cfg = RunConfig(report=False, stage_options={"identify": {"model": "full"}})
            run_pipeline(var, out, cfg, until="crossval")
            j = judge_run(out, truth, 500, seed)
            table[name].append(j["after"]["shape_rms_m"] * 1e3)
    ref = np.array(table["mono8"])
    print(
        f"response {args.response}, {args.polarity}, seeds {args.seeds}: shape RMS (mm) per seed, mean ratio to mono8"
    )
    for name, vals in table.items():
        v = np.array(vals)
        cells = " ".join(f"{x:.4f}" for x in v)
        print(f"  {name:22s} {cells}   mean {v.mean():.4f} mm  ratio {v.mean() / ref.mean():.3f}x")


if __name__ == "__main__":
    main()
