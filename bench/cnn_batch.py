"""Does a batch cheapen a CNN forward pass on the CPU? Per-image time of the default preset's
passes run one image at a time and as one run of several images.

    python -m bench.cnn_batch [--batches 4 8] [--images 8] [--rounds 4] [--json F]

The question behind batching concurrent requests in the service (frames arriving together run
as one batch through each network): it pays only where one run of B images costs less than B
runs of one. For each forward pass of the default preset (GeM on EfficientNet-Lite0 at 224 and
128 px, NetVLAD on Lite1 at 320 x 544, OLO on Lite0 at 416 x 416) on ONNX Runtime with one
compute thread (a service worker's setting), ``--images`` Gardens Point night_right frames,
preprocessed, are run as runs of 1 and as runs of each ``--batches`` size, the sizes
interleaved, ``--rounds`` times (the first round is a warm-up and not counted). Prints the
median ms per image and the ratio (above 1: the batch is cheaper per image).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

from bench.harness import add_json, machine, parser, write_record
from hmpf.backbones import backbone_class
from hmpf.backbones.onnx_runtime import INPUT, onnx_maps
from hmpf.config import build_methods, load_config
from hmpf.datasets import dataset_root, list_images
from hmpf.imageio import load_image, to_rgb
from hmpf.methods.cnn import CnnMethod
from hmpf.runtime import set_cnn_runtime, set_compute_threads


def per_image_ms(
    session: Any, layers: list[str], x: np.ndarray, sizes: list[int], rounds: int
) -> dict[int, float]:
    """Median ms per image of ``x`` run in runs of each size (interleaved per round)."""
    runs: dict[int, list[float]] = {b: [] for b in sizes}
    for r in range(rounds):
        for b in sizes:
            t0 = time.perf_counter()
            for i in range(0, len(x), b):
                session.run(layers, {INPUT: x[i : i + b]})
            if r:
                runs[b].append((time.perf_counter() - t0) * 1e3 / len(x))
    return {b: statistics.median(v) for b, v in runs.items()}


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--batches", type=int, nargs="+", default=[4, 8], help="run sizes")
    ap.add_argument("--images", type=int, default=8, help="frames (a multiple of each size)")
    ap.add_argument("--rounds", type=int, default=4, help="rounds, the first not counted")
    add_json(ap)
    ap.smoke(images=4, batches=[2, 4], rounds=2)
    args = ap.parse_args()
    set_cnn_runtime("onnx")
    set_compute_threads(1)
    config = load_config("default")
    frames = list_images(dataset_root() / "gardens_point" / "night_right")
    pick = np.linspace(0, len(frames) - 1, args.images).round().astype(int)
    images = [to_rgb(load_image(frames[i])) for i in pick]
    sizes = [1, *args.batches]
    print(f"Machine: {machine()}; preset default, digest {config.digest()[:12]}; one thread")
    passes: dict[str, Any] = {}
    for mid, m in build_methods(config).items():
        if not isinstance(m, CnnMethod):
            continue
        prep = backbone_class(m.cnn.backbone).preprocessor(m.cnn.backbone_options)
        assert prep is not None  # every exportable backbone preprocesses in numpy
        net, layers = m.backbone(), sorted(m.layers())
        for size in m.input_sizes():
            x = np.stack([prep(im, size) for im in images]).astype(np.float32)
            ms = per_image_ms(onnx_maps(net, layers, size).session, layers, x, sizes, args.rounds)
            name = f"{mid} {size[0]}x{size[1]}"
            passes[name] = {str(b): v for b, v in ms.items()}
            cells = ", ".join(f"runs of {b}: {v:.1f} ms ({ms[1] / v:.2f}x)" for b, v in ms.items())
            print(f"{name}: {cells}", flush=True)
    if args.json:
        write_record(args.json, {"passes": passes}, args, preset="default", config=config)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
