"""EfficientNet-Lite0 / Lite1 / Lite2 as the CNN backbone: recall and time, Gardens Point.

    python -m bench.backbones [--backbones efficientnet_lite0,...] [--sizes native|lite0]
                              [--time-images 10] [--json out.json]

For each backbone, the default config (``load_config("default")``) with every CNN method
(gem, netvlad, olo) switched to it, at the methods' default layers and input sizes for that
backbone (``--sizes lite0``: Lite0's input sizes on every backbone instead), on the three
whole Gardens Point protocols (``hmpf.datasets.GARDENS_POINT_PROTOCOLS``, +-2 frames):

* recall@1 of each method alone (the default's parameters: NetVLAD 32 centroids, OLO 100
  regions; over the whole database) and of the hierarchy;
* ms per image of each method's own extraction (decode excluded, ONNX Runtime, one compute
  thread, median over ``--time-images`` day_right images after a warm-up);
* the hierarchy's ms per query end to end on one thread
  (:func:`hmpf.evaluation.study.measure_query_ms`, day_right -> night_right) and the bytes an
  index stores per reference (``exact`` precision).

Features and scores come from :class:`~hmpf.evaluation.study.ScoreBank` (the evaluation's
``prepare``, cached in ``FeatureCache(default_cache_dir())``). Prints Markdown tables.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import (
    add_data,
    add_json,
    machine,
    parser,
    write_json,
)
from bench.inliers import bytes_per_reference
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS as PROTOCOLS
from hmpf.datasets import list_images
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache, extract_query
from hmpf.imageio import load_image
from hmpf.methods import Method
from hmpf.runtime import compute_threads, set_compute_threads

BACKBONES = ("efficientnet_lite0", "efficientnet_lite1", "efficientnet_lite2")
CNN = ("gem", "netvlad", "olo")
#: Lite0's default input sizes per method (``--sizes lite0``).
LITE0_SIZES = {"gem": [224, 224], "netvlad": [288, 512], "olo": [416, 416]}


def variant_config(base: HierarchyConfig, backbone: str, sizes: str) -> HierarchyConfig:
    """``base`` with every CNN method on ``backbone``."""
    methods = {m: dict(base.methods.get(m, {})) for m in base.method_ids}
    for m in CNN:
        if m in methods:
            methods[m]["backbone"] = backbone
            if sizes == "lite0":
                methods[m]["input_size"] = LITE0_SIZES[m]
    d = base.model_dump()
    d.update(name=f"default-{backbone}-{sizes}", methods=methods)
    return HierarchyConfig(**d)


def method_ms(methods: dict[str, Method], images: list[Path]) -> dict[str, float]:
    """Median ms per image of each method's own extraction, one compute thread."""
    previous = compute_threads()
    set_compute_threads(1)
    try:
        arrays = [load_image(p) for p in images]
        out = {}
        for mid, m in methods.items():
            times = []
            for i, img in enumerate([arrays[0], *arrays]):
                t0 = time.perf_counter()
                extract_query({mid: m}, img)
                if i:
                    times.append((time.perf_counter() - t0) * 1e3)
            out[mid] = float(np.median(times))
        return out
    finally:
        set_compute_threads(previous)


def main() -> int:
    ap = parser(__doc__)
    add_data(ap)
    ap.add_argument("--backbones", default=",".join(BACKBONES))
    ap.add_argument("--sizes", choices=("native", "lite0"), default="native")
    ap.add_argument("--time-images", type=int, default=10)
    add_json(ap)
    args = ap.parse_args()
    cache = FeatureCache(args.cache_dir)
    base = load_config("default")
    root = Path(args.datasets)
    timing_images = list_images(root / PROTOCOLS["gp_dr_nr"][0])[: args.time_images]
    print(machine(), flush=True)
    results: dict[str, Any] = {}
    timed: dict[str, tuple[HierarchyConfig, ScoreBank]] = {}
    for backbone in args.backbones.split(","):
        cfg = variant_config(base, backbone, args.sizes)
        row: dict[str, Any] = {"recall": {}, "config": cfg.model_dump()}
        t0 = time.perf_counter()
        for proto, (r, q) in PROTOCOLS.items():
            bank = ScoreBank.build(cfg, EvalData.frames(root / r, root / q, 2), cache=cache)
            rec = {m: bank.single_recall(m, [1])[1] for m in cfg.method_ids}
            rec["hierarchy"] = bank.run(cfg).recall_at_1
            row["recall"][proto] = rec
            if proto == "gp_dr_nr":
                timed[backbone] = cfg, bank
                row["bytes_per_reference"] = bytes_per_reference(bank, cfg)
            print(f"{backbone} {proto}: {json.dumps(rec)}", flush=True)
        row["wall_s"] = time.perf_counter() - t0
        results[backbone] = row
    # Timing last, every backbone back to back (nothing else should run meanwhile).
    print("timing", flush=True)
    for backbone, (cfg, bank) in timed.items():
        row = results[backbone]
        row["query"] = measure_query_ms(cfg, bank, images=args.time_images, threads=1)
        row["method_ms"] = method_ms(bank.methods, timing_images)
        print(f"{backbone}: query {row['query']}, method ms {row['method_ms']}", flush=True)
    print_tables(results, args.sizes)
    if args.json:
        write_json(args.json, results)  # keyed by backbone: no record around it
    return 0


def print_tables(results: dict[str, Any], sizes: str) -> None:
    protos = list(PROTOCOLS)
    print(f"\n### Each method alone (input sizes: {sizes}; recall@1, +-2 frames)\n")
    print("| backbone | method | " + " | ".join(protos) + " | mean | ms / image (1 thread) |")
    print("|---|---|" + "---|" * (len(protos) + 2))
    for b, row in results.items():
        for m in (*CNN, "gist"):
            if m not in row["recall"][protos[0]]:
                continue
            r = [row["recall"][p][m] for p in protos]
            cells = " | ".join(f"{x:.3f}" for x in r)
            print(f"| {b} | {m} | {cells} | {np.mean(r):.3f} | {row['method_ms'][m]:.1f} |")
    print("\n### Default hierarchy per backbone (recall@1, +-2 frames)\n")
    print(
        "| backbone | "
        + " | ".join(protos)
        + " | mean | ms / query (1 thread) | extract ms | bytes / reference |"
    )
    print("|---|" + "---|" * (len(protos) + 4))
    for b, row in results.items():
        r = [row["recall"][p]["hierarchy"] for p in protos]
        q = row["query"]
        print(
            f"| {b} | "
            + " | ".join(f"{x:.3f}" for x in r)
            + f" | {np.mean(r):.3f} | {q['total_ms']:.1f} | {q['extract_ms']:.1f} | "
            f"{row['bytes_per_reference']:.0f} |"
        )


if __name__ == "__main__":
    raise SystemExit(main())
