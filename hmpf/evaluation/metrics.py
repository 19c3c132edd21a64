"""Measures of a hierarchy's answers against ground truth: recall@N, the precision-recall
curve, one hierarchy's outcome per tier, precision at a threshold and the paired sign test.

Above :mod:`hmpf.evaluation.data`, below every other step of :mod:`hmpf.evaluation`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import binomtest

from hmpf.fusion import nan_argmax
from hmpf.hierarchy import Hierarchy, HierarchyResult, ScoreFn

__all__ = [
    "PR_THRESHOLDS",
    "RECALL_NS",
    "HierarchyOutcome",
    "median",
    "outcome_of",
    "paired_test",
    "pr_curve",
    "precision_recall_at",
    "recall_at_n",
    "run_queries",
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
    """Precision-recall over the quality score, the original's definition (spec §6.3,
    docs/spec/evaluation.md).

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


# -- one hierarchy's answers -------------------------------------------------------------------


@dataclass
class HierarchyOutcome:
    """One hierarchy's results on a set of queries, against the ground truth.

    Attributes:
        matches: (nq,) the answer per query (-1: none).
        quality: (nq,) the answer's Combined z-score.
        correct: (nq,) the answer is within the ground truth.
        tier_top1: per tier, recall@1 of the tier's mean score over the database (the
            original's ``recall_top1_by_level``).
        tier_recall: per tier, fraction of queries whose candidate list holds a correct one.
        mean_inputs: per tier, mean number of references scored (tier 1: the database).
        mean_candidates: per tier, mean length of the candidate list it passes on.
        tier_ms: per tier, median time per query (ms).
        fusion_ms: median time per query of the cross-tier fusion (ms).
    """

    matches: np.ndarray
    quality: np.ndarray
    correct: np.ndarray
    tier_top1: list[float]
    tier_recall: list[float]
    mean_inputs: list[float]
    mean_candidates: list[float] = field(default_factory=list)
    tier_ms: list[float] = field(default_factory=list)
    fusion_ms: float = float("nan")

    @property
    def recall_at_1(self) -> float:
        return float(self.correct.mean()) if self.correct.size else 0.0


def outcome_of(results: Sequence[HierarchyResult], gt: np.ndarray, n_db: int) -> HierarchyOutcome:
    """Summarise per-query hierarchy results against ``gt`` ((nq, n_db) bool)."""
    nq = len(results)
    match = np.array([r.match for r in results], dtype=np.int64)
    quality = np.array([r.quality for r in results], dtype=np.float64)
    correct = np.zeros(nq, dtype=bool)
    ok = match >= 0
    correct[ok] = gt[np.flatnonzero(ok), match[ok]]
    n_tiers = len(results[0].tiers) if results else 0
    top1, recall, inputs, cands, ms = [], [], [], [], []
    for t in range(n_tiers):
        tier = [r.tiers[t] for r in results]
        top1.append(float(np.mean([gt[q, nan_argmax(x.mean_score())] for q, x in enumerate(tier)])))
        recall.append(float(np.mean([gt[q, x.candidates].any() for q, x in enumerate(tier)])))
        inputs.append(float(np.mean([n_db if x.inputs is None else len(x.inputs) for x in tier])))
        cands.append(float(np.mean([len(x.candidates) for x in tier])))
        ms.append(median([x.time_ms for x in tier]))
    fusion = median([r.fusion_ms for r in results])
    return HierarchyOutcome(match, quality, correct, top1, recall, inputs, cands, ms, fusion)


def run_queries(
    hierarchy: Hierarchy, scorers: Iterable[ScoreFn], n_db: int
) -> tuple[list[HierarchyResult], float]:
    """Run ``hierarchy`` with each query's scorer; returns the results and the wall time (s)."""
    t0 = time.perf_counter()
    results = [hierarchy.run(score_fn, n_db) for score_fn in scorers]
    return results, time.perf_counter() - t0


def median(x: Sequence[float] | np.ndarray) -> float:
    """The median of the non-NaN values (NaN when there is none)."""
    a = np.asarray(x, dtype=np.float64)
    a = a[~np.isnan(a)]
    return float(np.median(a)) if a.size else float("nan")


# -- acceptance at a threshold, and two answer sets compared -----------------------------------


def precision_recall_at(
    quality: np.ndarray, correct: np.ndarray, threshold: float
) -> dict[str, Any]:
    """Precision, recall (correct accepted / all queries) and accepted share at a threshold."""
    q = np.nan_to_num(np.asarray(quality, np.float64), nan=-np.inf)
    c = np.asarray(correct, bool)
    acc = q >= threshold
    n_acc = int(acc.sum())
    tp = int((acc & c).sum())
    return {
        "precision": tp / n_acc if n_acc else None,
        "recall": tp / len(c) if len(c) else 0.0,
        "accepted": n_acc / len(c) if len(c) else 0.0,
        "n_accepted": n_acc,
        "n_queries": int(len(c)),
    }


def paired_test(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    """Exact two-sided sign (McNemar) test of two answer sets on the same queries.

    Args:
        a, b: (Q,) booleans, query answered correctly by A and by B.

    Returns:
        ``wins`` (A right, B wrong), ``losses`` (A wrong, B right) and ``p``, the probability
        of a split at least that uneven if A and B were equally good (1.0 with no
        discordant query).
    """
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError("both answer sets must cover the same queries")
    wins, losses = int(np.sum(a & ~b)), int(np.sum(~a & b))
    p = float(binomtest(wins, wins + losses, 0.5).pvalue) if wins + losses else 1.0
    return {"wins": wins, "losses": losses, "p": p}
