"""Evaluation of single methods, the hierarchy and flat fusion against ground truth.

Reports what the paper reports (``recall_final``, ``recall_by_level``,
``recall_top1_by_level``, the precision-recall curve over the quality score; METHODS.md §6) and
more: recall@N of every method alone, flat-fusion recall, and time per stage.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.config import HierarchyConfig, build_methods
from hmpf.datasets import frame_ground_truth, list_images
from hmpf.features import FeatureCache, extract_images, fit_methods
from hmpf.fusion import flat_fusion, nan_argmax, zscore
from hmpf.hierarchy import Hierarchy, HierarchyResult, feature_scorer
from hmpf.methods import Method

__all__ = [
    "RECALL_NS",
    "EvalData",
    "evaluate",
    "format_report",
    "pr_curve",
    "recall_at_n",
]

RECALL_NS = (1, 5, 10, 20, 50, 100)
PR_THRESHOLDS = np.arange(0.0, 50.0 + 1e-9, 0.5)  # the original's 0:0.5:50


def recall_at_n(
    scores: np.ndarray, gt: np.ndarray, ns: Sequence[int] = RECALL_NS, higher_is_better: bool = True
) -> dict[int, float]:
    """Fraction of queries with a correct reference among their N best (ties -> lower index).

    Args:
        scores: (nq, nd) scores of every query against every reference.
        gt: (nq, nd) boolean ground truth.
    """
    s = np.asarray(scores, dtype=np.float64)
    key = -s if higher_is_better else s
    key = np.where(np.isnan(key), np.inf, key)
    order = np.argsort(key, axis=1, kind="stable")
    hits = np.take_along_axis(gt, order, axis=1)
    first = np.where(hits.any(axis=1), hits.argmax(axis=1), np.iinfo(np.int64).max)
    return {n: float(np.mean(first < n)) for n in ns}


def pr_curve(correct: np.ndarray, quality: np.ndarray) -> dict[str, Any]:
    """Precision-recall over the quality score, the original's definition (METHODS.md §6).

    A query is predicted when ``quality > threshold``; wrong predictions are FP, every
    unpredicted query is FN (there are no true negatives), so recall = TP / n_queries.
    """
    c = np.asarray(correct, dtype=bool)
    q = np.nan_to_num(np.asarray(quality, dtype=np.float64), nan=-np.inf)
    pred = q[None, :] > PR_THRESHOLDS[:, None]
    tp = (pred & c[None, :]).sum(1).astype(np.float64)
    fp = (pred & ~c[None, :]).sum(1).astype(np.float64)
    fn = len(c) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = tp / (tp + fp)
        recall = tp / (tp + fn)
        f1 = 2 * tp / (2 * tp + fp + fn)
    p2 = np.append(precision[~np.isnan(precision)], 1.0)
    r2 = recall[: len(p2)]
    p2, r2 = p2[::-1], r2[::-1]
    if len(r2) == len(p2) - 1:
        r2 = np.insert(r2, 0, 0.0)
    auc = float(np.trapezoid(p2, r2)) if len(p2) > 1 else 0.0
    perfect = recall[(precision == 1.0) & (tp > 0)]
    return {
        "auc": auc,
        "max_f1": float(np.nanmax(f1)) if np.isfinite(f1).any() else 0.0,
        "recall_at_100_precision": float(perfect.max()) if perfect.size else 0.0,
        "thresholds": PR_THRESHOLDS.tolist(),
        "precision": [None if np.isnan(x) else float(x) for x in precision],
        "recall": recall.tolist(),
    }


@dataclass
class EvalData:
    """Everything an evaluation needs: images, ground truth and a description of it."""

    reference: list[Path]
    query: list[Path]
    gt: np.ndarray  # (n_query, n_ref) bool
    ground_truth: str  # e.g. "frames +-2"

    @classmethod
    def frames(cls, reference: str | Path, query: str | Path, tolerance: int) -> EvalData:
        """Two frame-aligned traverses (image folders): a match is within +-``tolerance``."""
        refs, qrys = list_images(reference), list_images(query)
        gt = frame_ground_truth(len(qrys), len(refs), tolerance)
        return cls(refs, qrys, gt, f"frames +-{tolerance}")


def _full_scores(method: Method, queries: Any, db: Any) -> np.ndarray:
    """(nq, nd) raw scores of every query against the whole database."""
    if method.kind == "global":
        return method.pairwise(queries, db)  # type: ignore[attr-defined]
    return np.stack([method.scores(q, db) for q in queries])


def _median(x: Sequence[float] | np.ndarray) -> float:
    a = np.asarray(x, dtype=np.float64)
    a = a[~np.isnan(a)]
    return float(np.median(a)) if a.size else float("nan")


def evaluate(
    config: HierarchyConfig,
    data: EvalData,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    skip_curves: Sequence[str] = (),
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate every method alone, the hierarchy and flat fusion; returns the JSON report.

    ``skip_curves`` lists method ids whose whole-database score matrix is not computed (their
    recall@N is omitted and flat fusion then uses the remaining methods; the report says so).
    """
    methods = build_methods(config)
    gt = data.gt
    t0 = time.perf_counter()
    # Fitted parameters come from the references only, never from the queries.
    fitted = fit_methods(methods, data.reference, cache=cache)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref = extract_images(
        data.reference, methods, cache=cache, workers=workers, progress=progress, desc="references"
    )
    qry = extract_images(
        data.query, methods, cache=cache, workers=workers, progress=progress, desc="queries"
    )
    extraction_s = time.perf_counter() - t0
    db = {m: methods[m].stack(ref.features[m]) for m in methods}
    q_sets = {m: methods[m].stack(qry.features[m]) for m in methods}
    n_db, n_q = len(data.reference), len(data.query)

    # -- the hierarchy, per query, scoring on demand (timed independently of the curves) ---
    hier = Hierarchy(config, methods)
    results: list[HierarchyResult] = []
    t0 = time.perf_counter()
    for qi in range(n_q):
        score_fn = feature_scorer(methods, {m: q_sets[m][qi] for m in methods}, db)
        results.append(hier.run(score_fn, n_db))
    hierarchy_s = time.perf_counter() - t0

    # -- every method alone over the whole database ---------------------------------------
    full: dict[str, np.ndarray] = {}
    method_report: dict[str, Any] = {}
    t0 = time.perf_counter()
    for mid, m in methods.items():
        entry: dict[str, Any] = {
            "type": type(m).name,
            "kind": m.kind,
            "higher_is_better": m.higher_is_better,
            "extract_ms_per_image": _median(np.concatenate([ref.ms[mid], qry.ms[mid]])),
        }
        if mid not in skip_curves:
            ts = time.perf_counter()
            full[mid] = _full_scores(m, q_sets[mid], db[mid])
            entry["match_ms_per_query_full_db"] = (time.perf_counter() - ts) * 1e3 / max(1, n_q)
            entry["recall_at"] = {
                str(k): v
                for k, v in recall_at_n(full[mid], gt, RECALL_NS, m.higher_is_better).items()
            }
        method_report[mid] = entry
    curves_s = time.perf_counter() - t0

    # -- flat fusion baseline ----------------------------------------------------------------
    flat_ids = [m for m in config.method_ids if m in full]
    flat_match = np.zeros(n_q, dtype=np.int64)
    flat_quality = np.zeros(n_q)
    if flat_ids:
        for qi in range(n_q):
            fused = flat_fusion(
                [full[m][qi] for m in flat_ids],
                [methods[m].higher_is_better for m in flat_ids],
                faithful=config.faithful,
            )
            flat_match[qi] = nan_argmax(fused)
            z = zscore(fused)
            flat_quality[qi] = z[flat_match[qi]]

    # -- metrics -------------------------------------------------------------------------------
    qidx = np.arange(n_q)
    match = np.array([r.match for r in results])
    quality = np.array([r.quality for r in results])
    correct = gt[qidx, match] & (match >= 0)
    tiers = []
    for t, tier in enumerate(config.tiers):
        cand_hit = [bool(gt[qi, r.tiers[t].candidates].any()) for qi, r in enumerate(results)]
        top1 = [bool(gt[qi, nan_argmax(r.tiers[t].mean_score())]) for qi, r in enumerate(results)]
        tiers.append(
            {
                "methods": list(tier.methods),
                "k": tier.k,
                "recall": float(np.mean(cand_hit)),
                "top1_recall": float(np.mean(top1)),
                "mean_candidates_out": float(
                    np.mean([len(r.tiers[t].candidates) for r in results])
                ),
                "ms_per_query": _median([r.tiers[t].time_ms for r in results]),
            }
        )
    flat_correct = gt[qidx, flat_match]
    report: dict[str, Any] = {
        "config": {
            "name": config.name,
            "mode": config.mode,
            "sha256": config.digest(),
            "resolved": config.model_dump(),
        },
        "protocol": {
            "reference": str(Path(data.reference[0]).parent),
            "query": str(Path(data.query[0]).parent),
            "n_reference": n_db,
            "n_query": n_q,
            "ground_truth": data.ground_truth,
            "queries_without_ground_truth": int((~gt.any(axis=1)).sum()),
        },
        "methods": method_report,
        "hierarchy": {
            "combined_recall_at_1": float(correct.mean()),
            "final_tier_recall_at_1": tiers[-1]["top1_recall"],
            "flat_recall_at_1": float(flat_correct.mean()) if flat_ids else None,
            "flat_methods": flat_ids,
            "tiers": tiers,
            "pr": pr_curve(correct, quality),
            "flat_pr": pr_curve(flat_correct, flat_quality) if flat_ids else None,
            "matches": match.tolist(),
            "quality": [None if np.isnan(x) else float(x) for x in quality],
        },
        "timing_ms": {
            "decode_per_image": _median([ref.decode_ms, qry.decode_ms]),
            "extract_per_image": {m: method_report[m]["extract_ms_per_image"] for m in methods},
            "tiers_per_query": [t["ms_per_query"] for t in tiers],
            "fusion_per_query": _median([r.fusion_ms for r in results]),
            "hierarchy_per_query": hierarchy_s * 1e3 / max(1, n_q),
        },
        "wall_s": {
            "fit": fit_s,
            "extraction": extraction_s,
            "hierarchy": hierarchy_s,
            "extraction_plus_hierarchy": extraction_s + hierarchy_s,
            "single_method_curves": curves_s,
        },
        "cache": {"reference_cached": ref.cached, "query_cached": qry.cached},
        "fitted_methods": fitted,
    }
    return report


def format_report(report: dict[str, Any]) -> str:
    """Human-readable tables of a report."""
    lines = []
    p = report["protocol"]
    lines.append(
        f"{report['config']['name']} ({report['config']['mode']}): {p['reference']} -> {p['query']}"
        f"  [{p['n_reference']} refs, {p['n_query']} queries, ground truth {p['ground_truth']}]"
    )
    lines.append("")
    header = "method".ljust(12) + "".join(f"R@{n}".rjust(8) for n in RECALL_NS) + "  extract ms/img"
    lines.append(header)
    for mid, e in report["methods"].items():
        rec = e.get("recall_at")
        cells = (
            "".join(f"{rec[str(n)]:8.3f}" for n in RECALL_NS)
            if rec
            else "  (no whole-database curve)"
        )
        lines.append(mid.ljust(12) + cells + f"  {e['extract_ms_per_image']:10.1f}")
    lines.append("")
    h = report["hierarchy"]
    lines.append("tier  methods              k   cand.recall  top1.recall  ms/query")
    for i, t in enumerate(h["tiers"], start=1):
        lines.append(
            f"{i:<5} {'+'.join(t['methods']):<20} {t['k']:<4} {t['recall']:11.3f}"
            f"  {t['top1_recall']:11.3f}  {t['ms_per_query']:8.2f}"
        )
    lines.append("")
    flat = h["flat_recall_at_1"]
    lines.append(f"Combined recall@1   {h['combined_recall_at_1']:.3f}")
    lines.append(f"final tier recall@1 {h['final_tier_recall_at_1']:.3f}")
    lines.append(f"flat fusion recall@1 {flat:.3f}" if flat is not None else "flat fusion: n/a")
    pr = h["pr"]
    lines.append(
        f"PR (quality): AUC {pr['auc']:.3f}  max F1 {pr['max_f1']:.3f}  "
        f"recall@100%P {pr['recall_at_100_precision']:.3f}"
    )
    w = report["wall_s"]
    tm = report["timing_ms"]
    lines.append(
        f"time: extraction {w['extraction']:.1f} s, hierarchy {w['hierarchy']:.1f} s "
        f"({tm['hierarchy_per_query']:.1f} ms/query), single-method curves "
        f"{w['single_method_curves']:.1f} s"
    )
    return "\n".join(lines)
