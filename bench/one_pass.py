"""One forward pass per query: the default hierarchy's CNN methods at one shared input size.

    python -m bench.one_pass [--images 20] [--variants default s288x512 ...] [--out F]

The default hierarchy reads EfficientNet-Lite0 at three input sizes (GeM 224 x 224, NetVLAD
288 x 512, OLO 416 x 416): three forward passes per query. Methods on one backbone and one
input size share a pass (``Method.group_key``), so giving the three methods one size makes
one pass. For each variant:

* recall@1 of the hierarchy on the training and the test part of every Gardens Point protocol
  (``split_data``: alternating stretches of 20 frames, each part its own map; +-2 frames),
  and on the whole protocols (200 references, 200 queries);
* the query's extraction on one compute thread (``extract_query``: every method, Gist
  included, as the service extracts a query), median ms over ``--images`` day_right images,
  with the default CNN runtime (ONNX Runtime when this was measured).

Choice rule (training parts only): the fastest variant whose mean training recall is at
least the three-pass default's minus 0.5 points. Its test recall is then compared with the
default's by an exact paired sign test on the pooled test queries of the three protocols;
every variant is also compared with the default on the whole protocols (600 queries pooled),
the maps the accuracy goal is stated on. Measured 2026-11-26: the training rule picks
224 x 384 (tied on the test parts, p = 0.54), but on the whole protocols 224 x 384 and
288 x 512 lose 3.5 and 4.8 points pooled (p = 0.046 and 0.002): the default keeps its three
passes and the one-pass hierarchy is the ``fast`` preset.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import (
    add_cache_dir,
    add_json,
    add_protocols,
    machine,
    parser,
    protocol_data,
    write_json,
)
from hmpf.config import HierarchyConfig, build_methods, load_config, parse_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images
from hmpf.evaluation.calibrate import paired_test
from hmpf.evaluation.evaluate import EvalData, evaluate
from hmpf.evaluation.study import split_data
from hmpf.features import FeatureCache, extract_query
from hmpf.imageio import load_image
from hmpf.methods.base import fit_many
from hmpf.methods.cnn import CnnMethod
from hmpf.runtime import (
    set_cnn_runtime,
    set_compute_threads,
)

CNN_METHODS = ("gem", "netvlad", "olo")
#: variant name -> input size (rows, cols) per CNN method; None: the method's own default.
VARIANTS: dict[str, dict[str, tuple[int, int] | None]] = {
    "default": {m: None for m in CNN_METHODS},
    "s224x384": {m: (224, 384) for m in CNN_METHODS},
    "s256x448": {m: (256, 448) for m in CNN_METHODS},
    "s288x512": {m: (288, 512) for m in CNN_METHODS},
    "s320x576": {m: (320, 576) for m in CNN_METHODS},
    "s416x416": {m: (416, 416) for m in CNN_METHODS},
    "two_pass": {"gem": (288, 512), "netvlad": (288, 512), "olo": None},
}


def variant_config(sizes: dict[str, tuple[int, int] | None]) -> HierarchyConfig:
    """The default hierarchy with each CNN method's input size set as given."""
    data = load_config("default").model_dump(exclude_unset=True)
    methods = data.setdefault("methods", {})
    for m, size in sizes.items():
        if size is not None:
            methods.setdefault(m, {})["input_size"] = list(size)
    return parse_config(data, "one_pass variant")


def passes(config: HierarchyConfig) -> int:
    """Forward passes per query: distinct (backbone, input size) groups of CNN methods."""
    methods = build_methods(config)
    return len({m.group_key() for m in methods.values() if isinstance(m, CnnMethod)})


def query_ms(config: HierarchyConfig, images: list[np.ndarray], fit: list[np.ndarray]) -> float:
    """Median ms of one query's extraction (every method) on one thread."""
    fitted = build_methods(config)
    fit_many({m: f for m, f in fitted.items() if f.requires_fit()}, fit)
    set_compute_threads(1)
    try:
        extract_query(fitted, images[0])  # warm-up: runtime session, first allocation
        runs = []
        for im in images:
            t = time.perf_counter()
            extract_query(fitted, im)
            runs.append((time.perf_counter() - t) * 1e3)
    finally:
        set_compute_threads(os.cpu_count() or 1)
    return statistics.median(runs)


def correct_flags(config: HierarchyConfig, data: EvalData, cache: FeatureCache) -> np.ndarray:
    rep = evaluate(config, data, cache=cache, skip_curves=list(config.method_ids))
    matches = np.array(rep["hierarchy"]["matches"])
    return data.gt[np.arange(len(matches)), matches]


Parts = dict[str, tuple[EvalData, EvalData]]


def add_recalls(
    row: dict[str, Any],
    config: HierarchyConfig,
    full: dict[str, EvalData],
    parts: Parts,
    cache: FeatureCache,
) -> None:
    """recall@1 per protocol on the training and test parts and the whole protocols, their
    means and the pooled per-query flags, into ``row``."""
    for part_i, part in enumerate(("train", "test", "whole")):
        flags = {
            p: correct_flags(config, full[p] if part == "whole" else parts[p][part_i], cache)
            for p in parts
        }
        row[part] = {p: float(f.mean()) for p, f in flags.items()}
        row[f"{part}_mean"] = float(np.mean(list(row[part].values())))
        row[f"{part}_flags"] = np.concatenate([flags[p] for p in parts]).tolist()


def print_table(out: dict[str, Any], parts: Parts, images: int) -> None:
    print(f"\nQuery extraction on one thread, median of {images} images; recall@1 (+-2):\n")
    print(
        "| variant | passes | ms / query | train: " + " / ".join(parts) + " (mean) "
        "| test: " + " / ".join(parts) + " (mean) |"
    )
    print("|---|---:|---:|---|---|")
    for v, row in out.items():
        tr = " / ".join(f"{row['train'][p]:.3f}" for p in parts)
        te = " / ".join(f"{row['test'][p]:.3f}" for p in parts)
        print(
            f"| {v} | {row['passes']} | {row['query_ms']:.1f} | {tr} ({row['train_mean']:.3f}) "
            f"| {te} ({row['test_mean']:.3f}) |"
        )


def print_choice(out: dict[str, Any], parts: Parts) -> None:
    """The variant chosen on the training parts, and every variant on the whole protocols,
    against the default."""
    base = out["default"]
    ok = [v for v in out if out[v]["train_mean"] >= base["train_mean"] - 0.005]
    chosen = min(ok, key=lambda v: out[v]["query_ms"])
    test = paired_test(np.array(out[chosen]["test_flags"]), np.array(base["test_flags"]))
    print(
        f"\nChosen on the training parts: {chosen} (fastest within 0.5 points of default's "
        f"training recall). Test parts, pooled ({len(base['test_flags'])} queries): "
        f"{out[chosen]['test_mean']:.3f} vs {base['test_mean']:.3f}; paired sign test: "
        f"{test['wins']} wins, {test['losses']} losses, p = {test['p']:.3f}"
    )
    print(
        "\nWhole protocols (every reference in the map, every query), against the default "
        f"({base['whole_mean']:.3f} mean; pooled {len(base['whole_flags'])} queries):\n"
    )
    print("| variant | " + " / ".join(parts) + " (mean) | wins / losses | p |")
    print("|---|---|---:|---:|")
    for v, row in out.items():
        t = paired_test(np.array(row["whole_flags"]), np.array(base["whole_flags"]))
        wh = " / ".join(f"{row['whole'][p]:.3f}" for p in parts)
        print(
            f"| {v} | {wh} ({row['whole_mean']:.3f}) | {t['wins']} / {t['losses']} | {t['p']:.3f} |"
        )


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--images", type=int, default=20, help="images timed (day_right)")
    ap.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    add_cache_dir(ap)
    add_json(ap, "--out", type=Path, help="write the figures as JSON")
    ap.add_argument("--no-recall", action="store_true", help="timings only")
    add_protocols(ap, default=GARDENS_POINT_PROTOCOLS)
    args = ap.parse_args()
    set_cnn_runtime("onnx")
    print(f"Machine: {machine()}", flush=True)
    refs = list_images(dataset_root() / "gardens_point" / "day_right")
    pick = np.linspace(0, len(refs) - 1, args.images).round().astype(int)
    images = [load_image(refs[i]) for i in pick]
    fit = [load_image(p) for p in refs[::7]]
    cache = FeatureCache(args.cache_dir)
    full = {name: protocol_data(name) for name in args.protocols}
    parts: Parts = {name: split_data(data) for name, data in full.items()}
    out: dict[str, Any] = {}
    for v in args.variants:
        config = variant_config(VARIANTS[v])
        row: dict[str, Any] = {"passes": passes(config), "query_ms": query_ms(config, images, fit)}
        out[v] = row
        if args.no_recall:
            print(f"{v}: {row['passes']} pass(es), {row['query_ms']:.1f} ms/query", flush=True)
            continue
        add_recalls(row, config, full, parts, cache)
        print(
            f"{v}: {row['passes']} pass(es), {row['query_ms']:.1f} ms/query, "
            f"train {row['train_mean']:.3f}, test {row['test_mean']:.3f}, "
            f"whole {row['whole_mean']:.3f}",
            flush=True,
        )
    if args.no_recall:
        return 0
    print_table(out, parts, args.images)
    if "default" in out:
        print_choice(out, parts)
    if args.out:
        write_json(args.out, out)  # keyed by variant: no record around it
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
