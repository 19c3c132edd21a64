"""Recall@1 of every method alone and of the hierarchy on the shared datasets.

    python -m bench.accuracy [--config configs/handcrafted.yaml] [--protocols ...] [--out F]

Prints one table per protocol (from ``hmpf-eval``) and a summary in Markdown, ready for the
README, and writes every full report to ``--out`` (JSON). Ground truth: +-2 frames on every
protocol (frame-aligned traverses); Nordland uses all 3576 frames (dark frames included) and
computes KAZE's whole-database curve too (about 35 min on 2 cores: ~230 keypoints per
upsampled thumbnail); ``--skip-curves kaze`` leaves it out.
"""

from __future__ import annotations

import time
from typing import Any

from bench.harness import (
    ROOT,
    add_data,
    add_json,
    add_protocols,
    machine,
    parser,
    protocol_data,
    write_record,
)
from hmpf.config import HierarchyConfig, load_config
from hmpf.evaluation.evaluate import evaluate, format_report
from hmpf.features import FeatureCache


def run(config: HierarchyConfig, args: Any) -> dict[str, Any]:
    """Protocol -> ``hmpf-eval``'s full report (each printed as it is done)."""
    cache = FeatureCache(args.cache_dir)
    reports = {}
    for name in args.protocols:
        t0 = time.perf_counter()
        rep = evaluate(
            config,
            protocol_data(name, args.datasets, args.tolerance),
            cache=cache,
            workers=args.workers,
            progress=True,
            skip_curves=args.skip_curves,
        )
        rep["bench_wall_s"] = time.perf_counter() - t0
        reports[name] = rep
        print(f"\n=== {name} ===")
        print(format_report(rep), flush=True)
    return reports


def summary(ids: list[str], reports: dict[str, Any]) -> str:
    """The Markdown summary: recall@1 per protocol, then the time per stage."""
    head = ["protocol", *ids, "Combined", "final tier", "flat", "tier recalls", "ms/query"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, rep in reports.items():
        h = rep["hierarchy"]
        single = [rep["methods"][m].get("recall_at", {}).get("1") for m in ids]
        cells = [f"{x:.3f}" if x is not None else "-" for x in single]
        tiers = " / ".join(f"{t['recall']:.2f}" for t in h["tiers"])
        lines.append(
            f"| {name} | "
            + " | ".join(cells)
            + f" | **{h['combined_recall_at_1']:.3f}** | {h['final_tier_recall_at_1']:.3f}"
            + f" | {h['flat_recall_at_1']:.3f} | {tiers}"
            + f" | {rep['timing_ms']['hierarchy_per_query']:.1f} |"
        )
    lines.append("\nTime per stage (median ms):")
    for name, rep in reports.items():
        t = rep["timing_ms"]
        ext = ", ".join(f"{m} {v:.1f}" for m, v in t["extract_per_image"].items())
        tiers = ", ".join(f"tier {i + 1} {v:.2f}" for i, v in enumerate(t["tiers_per_query"]))
        lines.append(
            f"- {name}: extraction per image: {ext}; matching per query: {tiers}, "
            f"fusion {t['fusion_per_query']:.3f}"
        )
    return "\n".join(lines)


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--config", default=str(ROOT / "configs" / "handcrafted.yaml"))
    add_protocols(ap)
    ap.add_argument("--tolerance", type=int, default=2)
    add_data(ap)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--skip-curves", nargs="*", default=[], metavar="METHOD")
    add_json(ap, "--out", default=str(ROOT / "results" / "accuracy.json"), help="JSON report")
    ap.smoke(protocols=["gp_dr_nr"])
    args = ap.parse_args()
    config = load_config(args.config)
    reports = run(config, args)
    print(
        f"\nMachine: {machine()}\nConfig: {args.config}, ground truth +-{args.tolerance} frames\n"
    )
    print(summary(config.method_ids, reports))
    out = write_record(args.out, {"config": args.config, "reports": reports}, args, config=config)
    print(f"\nfull reports: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
