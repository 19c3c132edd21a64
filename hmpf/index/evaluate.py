"""Evaluation of queries against a built index (``hmpf-eval --index``).

Runs exactly what the service runs per query (:meth:`IndexReader.scorer` in the hierarchy)
and reports the hierarchy's recall, per-tier recall, the PR curve over the quality score and
timings. Single-method curves and flat fusion need whole-database score matrices and are left
to the in-memory evaluation (``hmpf-eval`` without ``--index``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.evaluate import pr_curve
from hmpf.features import FeatureCache, extract_images
from hmpf.fusion import nan_argmax
from hmpf.index.reader import IndexReader

__all__ = ["evaluate_index", "format_index_report"]


def evaluate_index(
    reader: IndexReader,
    queries: Sequence[Path],
    gt: np.ndarray,
    ground_truth: str,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the hierarchy for every query against ``reader``; ``gt`` is (n_query, n_ref)."""
    t0 = time.perf_counter()
    qry = extract_images(
        queries, reader.methods, cache=cache, workers=workers, progress=progress, desc="queries"
    )
    extraction_s = time.perf_counter() - t0
    hier = reader.hierarchy()
    t0 = time.perf_counter()
    results = [
        hier.run(reader.scorer({m: qry.features[m][qi] for m in reader.methods}), reader.n)
        for qi in range(len(queries))
    ]
    hierarchy_s = time.perf_counter() - t0
    qidx = np.arange(len(queries))
    match = np.array([r.match for r in results])
    quality = np.array([r.quality for r in results])
    correct = gt[qidx, match] & (match >= 0)
    tiers = []
    for t, tier in enumerate(reader.config.tiers):
        tiers.append(
            {
                "methods": list(tier.methods),
                "k": tier.k,
                "recall": float(
                    np.mean([gt[q, r.tiers[t].candidates].any() for q, r in enumerate(results)])
                ),
                "top1_recall": float(
                    np.mean(
                        [gt[q, nan_argmax(r.tiers[t].mean_score())] for q, r in enumerate(results)]
                    )
                ),
                "ms_per_query": float(np.median([r.tiers[t].time_ms for r in results])),
            }
        )
    return {
        "index": {"path": str(reader.root), "version": reader.version, "n_reference": reader.n},
        "config": {"name": reader.config.name, "sha256": reader.config.digest()},
        "protocol": {
            "query": str(Path(queries[0]).parent),
            "n_query": len(queries),
            "ground_truth": ground_truth,
        },
        "hierarchy": {
            "combined_recall_at_1": float(correct.mean()),
            "tiers": tiers,
            "pr": pr_curve(correct, quality),
            "matches": [reader.refs.names[m] if m >= 0 else None for m in match],
        },
        "wall_s": {"extraction": extraction_s, "hierarchy": hierarchy_s},
        "timing_ms": {"hierarchy_per_query": hierarchy_s * 1e3 / max(1, len(queries))},
    }


def format_index_report(report: dict[str, Any]) -> str:
    """Human-readable summary of :func:`evaluate_index`'s report."""
    i, p, h = report["index"], report["protocol"], report["hierarchy"]
    lines = [
        f"{report['config']['name']}: index {i['path']} ({i['version']}, {i['n_reference']} refs)"
        f" <- {p['query']} [{p['n_query']} queries, ground truth {p['ground_truth']}]",
        "tier  methods              k   cand.recall  top1.recall  ms/query",
    ]
    for n, t in enumerate(h["tiers"], start=1):
        lines.append(
            f"{n:<5} {'+'.join(t['methods']):<20} {t['k']:<4} {t['recall']:11.3f}"
            f"  {t['top1_recall']:11.3f}  {t['ms_per_query']:8.2f}"
        )
    pr = h["pr"]
    lines += [
        f"Combined recall@1   {h['combined_recall_at_1']:.3f}",
        f"PR (quality): AUC {pr['auc']:.3f}  max F1 {pr['max_f1']:.3f}  "
        f"recall@100%P {pr['recall_at_100_precision']:.3f}",
        f"time: query extraction {report['wall_s']['extraction']:.1f} s, hierarchy "
        f"{report['wall_s']['hierarchy']:.1f} s "
        f"({report['timing_ms']['hierarchy_per_query']:.1f} ms/query)",
    ]
    return "\n".join(lines)
