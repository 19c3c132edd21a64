"""CNN forward passes in torch and in ONNX Runtime: speed on one thread, and recall@1.

    python -m bench.cnn_runtime [--images 20] [--protocols gp_dr_nr ...] [--no-recall]

* Speed, one compute thread (a service worker's or an extraction worker's setting), one
  image at a time as for a query, on the same real Gardens Point images for both runtimes
  (median ms per image, one run each, after a warm-up image):
  - per input size: preprocessing + the forward pass of the layers the default hierarchy
    reads at that size (224 x 224 GeM, 288 x 512 NetVLAD, 416 x 416 OLO);
  - per method: its whole extraction (preprocessing + forward + descriptor), the default
    hierarchy's CNN methods fitted on 29 references (the same parameters for both runtimes);
  - per query: every method of the default hierarchy (Gist included), as the service
    extracts a query (``extract_query``).
* Recall@1 of the default hierarchy on the three Gardens Point protocols with each runtime
  (``hmpf.evaluation.evaluate``, +-2 frames), fitted and extracted by that runtime: the
  descriptor cache keys them apart (``Method.descriptor_key``), so neither reads the other's
  descriptors; also how many answers differ between the two.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

import numpy as np
import onnxruntime
import torch

from bench.harness import add_cache_dir, machine, median_ms, parser
from hmpf.config import build_methods, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images
from hmpf.evaluation.evaluate import EvalData, evaluate
from hmpf.features import FeatureCache, extract_query
from hmpf.imageio import load_image, to_rgb
from hmpf.methods.base import Method, extract_many, fit_many
from hmpf.methods.cnn import CnnMethod
from hmpf.runtime import (
    CNN_RUNTIMES,
    compute_threads,
    set_cnn_runtime,
    set_compute_threads,
)


def forward_fn(group: list[CnnMethod], runtime: str) -> Any:
    """Preprocessing + forward pass of ``group``'s layers at its size, one image per call."""
    head = group[0]
    net = head.backbone()
    size = head.input_size()
    layers = sorted({layer for m in group for layer in m.layers()})
    if runtime == "onnx":
        from hmpf.backbones.onnx_runtime import onnx_maps

        maps = onnx_maps(net, layers, size)
        return lambda im: maps(net.preprocess(to_rgb(im), size)[None])

    torch.set_num_threads(compute_threads())

    def run(im: np.ndarray) -> None:
        x = torch.from_numpy(net.preprocess(to_rgb(im), size)[None])
        with torch.inference_mode():
            net.forward_maps(x, layers)

    return run


def speed(images: list[np.ndarray], fitted: dict[str, Method]) -> None:
    cnn = {m: f for m, f in fitted.items() if isinstance(f, CnnMethod)}
    groups: dict[Any, list[CnnMethod]] = {}
    for m in cnn.values():
        groups.setdefault(m.group_key(), []).append(m)
    rows: list[tuple[str, float, float]] = []
    for group in groups.values():
        ms = {}
        for rt in CNN_RUNTIMES:
            set_cnn_runtime(rt)
            ms[rt] = median_ms(forward_fn(group, rt), images)
        rows_name = "x".join(map(str, group[0].input_size()))
        names = "+".join(m.name for m in group)
        rows.append((f"{rows_name} ({names})", ms["torch"], ms["onnx"]))
    for mid, m in cnn.items():
        ms = {}
        for rt in CNN_RUNTIMES:
            set_cnn_runtime(rt)
            ms[rt] = median_ms(lambda im, mid=mid, m=m: extract_many({mid: m}, [im]), images)
        rows.append((f"method {mid}", ms["torch"], ms["onnx"]))
    ms = {}
    for rt in CNN_RUNTIMES:
        set_cnn_runtime(rt)
        ms[rt] = median_ms(lambda im: extract_query(fitted, im), images)
    rows.append(("query: every method (" + ", ".join(fitted) + ")", ms["torch"], ms["onnx"]))
    print(f"\nms per image, one thread, {len(images)} images (median):\n")
    print("| what | torch | onnx | torch / onnx |")
    print("|---|---:|---:|---:|")
    for name, t, o in rows:
        print(f"| {name} | {t:.1f} | {o:.1f} | {t / o:.2f}x |")


def recall(protocols: list[str], cache_dir: str, workers: int | None) -> None:
    config = load_config("default")
    cache = FeatureCache(cache_dir)
    rows = []
    for name in protocols:
        ref_dir, q_dir = (dataset_root() / p for p in GARDENS_POINT_PROTOCOLS[name])
        data = EvalData.frames(ref_dir, q_dir, 2)
        rep = {}
        for rt in CNN_RUNTIMES:
            set_cnn_runtime(rt)
            t0 = time.perf_counter()
            rep[rt] = evaluate(config, data, cache=cache, workers=workers)
            print(f"  {name} {rt}: {time.perf_counter() - t0:.0f} s", flush=True)
        h = {rt: r["hierarchy"] for rt, r in rep.items()}
        differ = int(np.sum(np.array(h["torch"]["matches"]) != np.array(h["onnx"]["matches"])))
        single = {
            rt: " / ".join(
                f"{r['methods'][m]['recall_at']['1']:.3f}" for m in ("gem", "netvlad", "olo")
            )
            for rt, r in rep.items()
        }
        rows.append(
            f"| {name} | {h['torch']['combined_recall_at_1']:.3f} | "
            f"{h['onnx']['combined_recall_at_1']:.3f} | {differ} / {len(data.query)} | "
            f"{single['torch']} | {single['onnx']} |"
        )
    print(
        "\nRecall@1 of the default hierarchy (+-2 frames), each runtime fitting and extracting:\n"
    )
    print(
        "| protocol | torch | onnx | answers that differ | gem / netvlad / olo torch "
        "| gem / netvlad / olo onnx |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    print("\n".join(rows))


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--images", type=int, default=20, help="images timed (day_right)")
    ap.add_argument(
        "--protocols",
        nargs="*",
        default=list(GARDENS_POINT_PROTOCOLS),
        choices=list(GARDENS_POINT_PROTOCOLS),
    )
    ap.add_argument("--no-recall", action="store_true", help="timings only")
    add_cache_dir(ap)
    ap.add_argument("--workers", type=int, default=None, help="Gist extraction processes")
    args = ap.parse_args()
    print(f"Machine: {machine()}; torch {torch.__version__}, onnxruntime {onnxruntime.__version__}")
    gp = dataset_root() / "gardens_point"
    refs = list_images(gp / "day_right")
    pick = np.linspace(0, len(refs) - 1, args.images).round().astype(int)
    images = [load_image(refs[i]) for i in pick]
    fitted = build_methods(load_config("default"))
    set_cnn_runtime("torch")
    fit_refs = [load_image(p) for p in refs[::7]]
    fit_many({m: f for m, f in fitted.items() if f.requires_fit()}, fit_refs)
    set_compute_threads(1)
    speed(images, fitted)
    if not args.no_recall:
        set_compute_threads(os.cpu_count() or 1)  # not timed: every core
        recall(args.protocols, args.cache_dir, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
