"""Recall@1 of every method alone and of the hierarchy on the shared datasets.

    python bench/accuracy.py [--config configs/handcrafted.yaml] [--protocols ...] [--out F]

Prints one table per protocol (from ``hmpf-eval``) and a summary in Markdown, ready for the
README, and writes every full report to ``--out`` (JSON). Ground truth: +-2 frames on every
protocol (frame-aligned traverses); Nordland uses all 3576 frames (dark frames included) and
computes KAZE's whole-database curve too (about 35 min on 2 cores: ~230 keypoints per
upsampled thumbnail); ``--skip-curves kaze`` leaves it out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hmpf.config import load_config  # noqa: E402
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root  # noqa: E402
from hmpf.evaluation.evaluate import EvalData, evaluate, format_report  # noqa: E402
from hmpf.features import FeatureCache, default_cache_dir  # noqa: E402
from hmpf.runtime import machine_description as machine  # noqa: E402

PROTOCOLS = {
    **GARDENS_POINT_PROTOCOLS,
    "nordland_s_w": ("nordland_64x32/summer", "nordland_64x32/winter"),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "handcrafted.yaml"))
    ap.add_argument("--protocols", nargs="*", default=list(PROTOCOLS), choices=list(PROTOCOLS))
    ap.add_argument("--tolerance", type=int, default=2)
    ap.add_argument("--datasets", default=str(dataset_root()))
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--skip-curves", nargs="*", default=[], metavar="METHOD")
    ap.add_argument("--out", default=str(ROOT / "results" / "accuracy.json"))
    args = ap.parse_args()

    config = load_config(args.config)
    cache = FeatureCache(args.cache_dir)
    reports = {}
    for name in args.protocols:
        ref_dir, q_dir = (Path(args.datasets) / p for p in PROTOCOLS[name])
        t0 = time.perf_counter()
        rep = evaluate(
            config,
            EvalData.frames(ref_dir, q_dir, args.tolerance),
            cache=cache,
            workers=args.workers,
            progress=True,
            skip_curves=args.skip_curves,
        )
        rep["bench_wall_s"] = time.perf_counter() - t0
        reports[name] = rep
        print(f"\n=== {name} ===")
        print(format_report(rep), flush=True)

    ids = config.method_ids
    print(
        f"\nMachine: {machine()}\nConfig: {args.config}, ground truth +-{args.tolerance} frames\n"
    )
    head = ["protocol", *ids, "Combined", "final tier", "flat", "tier recalls", "ms/query"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, rep in reports.items():
        h = rep["hierarchy"]
        single = [rep["methods"][m].get("recall_at", {}).get("1") for m in ids]
        cells = [f"{x:.3f}" if x is not None else "-" for x in single]
        tiers = " / ".join(f"{t['recall']:.2f}" for t in h["tiers"])
        print(
            f"| {name} | "
            + " | ".join(cells)
            + f" | **{h['combined_recall_at_1']:.3f}** | {h['final_tier_recall_at_1']:.3f}"
            + f" | {h['flat_recall_at_1']:.3f} | {tiers}"
            + f" | {rep['timing_ms']['hierarchy_per_query']:.1f} |"
        )
    print("\nTime per stage (median ms):")
    for name, rep in reports.items():
        t = rep["timing_ms"]
        ext = ", ".join(f"{m} {v:.1f}" for m, v in t["extract_per_image"].items())
        tiers = ", ".join(f"tier {i + 1} {v:.2f}" for i, v in enumerate(t["tiers_per_query"]))
        print(
            f"- {name}: extraction per image: {ext}; matching per query: {tiers}, "
            f"fusion {t['fusion_per_query']:.3f}"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"machine": machine(), "config": args.config, "reports": reports}, indent=1)
    )
    print(f"\nfull reports: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
