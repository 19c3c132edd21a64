"""A hierarchy over every query of a score bank at once: the fast path of
:meth:`hmpf.evaluation.study.ScoreBank.run`.

:class:`~hmpf.hierarchy.Hierarchy` runs one query at a time on (n,) arrays, which is what the
service does. A calibration search runs thousands of hierarchies over the same hundred
queries of a few hundred references, and there the per-call overhead of a few dozen small
numpy calls per query is nearly all the time. This module runs the same steps on (queries,
references) matrices:

* a tier's methods are min-max normalised over the references it scored (a row-wise
  ``fmin`` / ``fmax``; elsewhere NaN), each method's top ``k`` is a stable row-wise sort
  (ties -> lower index, NaN last and skipped), a non-final tier's candidates are the union of
  its methods' lists in order, later repeats removed;
* the Combined score over the final candidates is computed for all the queries whose final
  list has the same length at once, so every reduction (min, max, mean, sample std) runs
  over a contiguous row of exactly the values the per-query code reduces, in the same order.

It gives **the same floats** as the per-query path (matches, quality, the per-tier figures of
:class:`~hmpf.evaluation.metrics.HierarchyOutcome`), which ``tests/hmpf/evaluation/
test_batch.py`` checks against :func:`~hmpf.evaluation.metrics.outcome_of` bit for bit. Only
the default mode is covered (faithful mode keeps duplicates in its unions and normalises over
them: it runs per query); nothing is timed (``tier_ms`` and ``fusion_ms`` are NaN). Queries
run in chunks of about :data:`CHUNK_ENTRIES` score entries, so the memory it adds is a few
such arrays per method and tier, whatever the bank's size.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hmpf.config import HierarchyConfig
from hmpf.evaluation.metrics import HierarchyOutcome, outcome_of
from hmpf.methods import Method

__all__ = ["batch_outcome"]


def _minmax_rows(x: np.ndarray, higher_is_better: bool) -> np.ndarray:
    """:func:`hmpf.fusion.minmax_normalise` (default mode) of every row of ``x``."""
    lo = np.fmin.reduce(x, axis=1, initial=np.nan)[:, None]
    hi = np.fmax.reduce(x, axis=1, initial=np.nan)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (x - lo) / (hi - lo) if higher_is_better else (hi - x) / (hi - lo)
    const = (hi == lo)[:, 0]
    if const.any():
        out[const] = np.where(np.isnan(x[const]), np.nan, 1.0)
    return out  # a row of NaN only (lo NaN) stays NaN


def _top_k_rows(s: np.ndarray, k: int) -> np.ndarray:
    """:func:`hmpf.fusion.top_k` of every row: (Q, min(k, n)) indices, -1 past a row's
    non-NaN entries."""
    if k <= 0 or s.shape[1] == 0:
        return np.zeros((s.shape[0], 0), dtype=np.int64)
    with np.errstate(invalid="ignore"):
        order = np.argsort(-s, axis=1, kind="stable")[:, :k]  # NaN sorts last
    order[np.isnan(np.take_along_axis(s, order, axis=1))] = -1
    return order.astype(np.int64)


def _union_rows(lists: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hmpf.fusion.union` (default mode) of every row's lists: (Q, L) indices in
    order, first occurrences only, -1 padded; and each row's length."""
    cat = np.concatenate(lists, axis=1)
    rows = np.arange(cat.shape[0])[:, None]
    # A repeat is equal to the entry before it once each row is sorted by value (stable: of
    # equal values, the earliest comes first), so no (Q, L, L) comparison is made.
    by_value = np.argsort(cat, axis=1, kind="stable")
    ordered = cat[rows, by_value]
    repeat = np.zeros(cat.shape, dtype=bool)
    repeat[rows, by_value[:, 1:]] = ordered[:, 1:] == ordered[:, :-1]
    keep = (cat >= 0) & ~repeat
    order = np.argsort(~keep, axis=1, kind="stable")
    out = np.take_along_axis(cat, order, axis=1)
    kept = np.take_along_axis(keep, order, axis=1)
    out[~kept] = -1
    return out, keep.sum(axis=1)


def _nan_argmax_rows(x: np.ndarray) -> np.ndarray:
    """:func:`hmpf.fusion.nan_argmax` of every row (first maximum, NaN skipped; all NaN: 0)."""
    return np.argmax(np.where(np.isnan(x), -np.inf, x), axis=1)


def _zscore_rows(v: np.ndarray) -> np.ndarray:
    """:func:`hmpf.fusion.zscore` of every row of a C-contiguous (Q, L) array."""
    if v.shape[1] == 1:
        return np.where(np.isnan(v), np.nan, 0.0)
    mean = v.mean(axis=1, keepdims=True)
    sd = v.std(axis=1, ddof=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (v - mean) / sd
    out[(sd == 0)[:, 0]] = 0.0
    out[np.isnan(v).any(axis=1)] = np.nan
    return out


#: Score entries (queries x references) of one chunk of queries: the batch holds a few arrays
#: of this size per method and tier, whatever the bank's size.
CHUNK_ENTRIES = 1 << 21


def batch_outcome(
    config: HierarchyConfig,
    methods: Mapping[str, Method],
    scores: Mapping[str, np.ndarray],
    gt: np.ndarray,
    *,
    chunk_entries: int = CHUNK_ENTRIES,
) -> HierarchyOutcome | None:
    """``config`` over every query of a bank: ``outcome_of`` of the per-query results.

    Args:
        config: the hierarchy; None is returned for faithful mode (run it per query).
        methods: method id -> instance (only ``higher_is_better`` is read).
        scores: method id -> (Q, N) raw scores of every query against every reference.
        gt: (Q, N) ground truth.
        chunk_entries: queries are run in chunks of about this many score entries.
    """
    if config.faithful:
        return None
    gt = np.asarray(gt, dtype=bool)
    nq, n_db = gt.shape
    if nq == 0:
        return outcome_of([], gt, n_db)
    step = max(1, chunk_entries // max(n_db, 1))
    parts = [
        _run_rows(
            config,
            methods,
            {m: scores[m][a : a + step] for m in config.method_ids},
            gt[a : a + step],
        )
        for a in range(0, nq, step)
    ]
    match = np.concatenate([p.match for p in parts])
    quality = np.concatenate([p.quality for p in parts])
    n_tiers = len(config.tiers)

    def mean(field: str, t: int) -> float:
        return float(np.mean(np.concatenate([getattr(p, field)[t] for p in parts])))

    correct = np.zeros(nq, dtype=bool)
    ok = match >= 0
    correct[ok] = gt[np.flatnonzero(ok), match[ok]]
    return HierarchyOutcome(
        match,
        quality,
        correct,
        [mean("top1", t) for t in range(n_tiers)],
        [mean("recall", t) for t in range(n_tiers)],
        [float(n_db)] + [mean("inputs", t) for t in range(n_tiers - 1)],
        [mean("cands", t) for t in range(n_tiers)],
        [float("nan")] * n_tiers,
        float("nan"),
    )


@dataclass
class _Rows:
    """Per query of a chunk: the answer, and per tier the figures ``outcome_of`` averages."""

    match: np.ndarray
    quality: np.ndarray
    top1: list[np.ndarray]  # the tier's mean score's best reference is right
    recall: list[np.ndarray]  # a right reference is among the tier's candidates
    inputs: list[np.ndarray]  # references a tier after the first scored
    cands: list[np.ndarray]  # candidates the tier passed on


def _run_rows(
    config: HierarchyConfig,
    methods: Mapping[str, Method],
    scores: Mapping[str, np.ndarray],
    gt: np.ndarray,
) -> _Rows:
    nq, n_db = gt.shape
    rows = np.arange(nq)[:, None]
    n_tiers = len(config.tiers)
    normed: list[dict[str, np.ndarray]] = []
    cands: list[np.ndarray] = []
    out_rows = _Rows(np.full(nq, -1, dtype=np.int64), np.full(nq, np.nan), [], [], [], [])
    inside: np.ndarray | None = None  # (Q, N): the references a later tier scores
    for t, tier in enumerate(config.tiers):
        norm: dict[str, np.ndarray] = {}
        for mid in tier.methods:
            raw = np.asarray(scores[mid], dtype=np.float64)
            x = raw if inside is None else np.where(inside, raw, np.nan)
            norm[mid] = _minmax_rows(x, methods[mid].higher_is_better)
        normed.append(norm)
        mean = np.mean([norm[m] for m in tier.methods], axis=0)
        if t < n_tiers - 1:
            out, length = _union_rows([_top_k_rows(norm[m], tier.k) for m in tier.methods])
        else:
            out = _top_k_rows(mean, tier.k)
            length = (out >= 0).sum(axis=1)
        cands.append(out)
        out_rows.top1.append(gt[np.arange(nq), _nan_argmax_rows(mean)])
        out_rows.recall.append((gt[rows, np.maximum(out, 0)] & (out >= 0)).any(axis=1))
        out_rows.cands.append(length)
        if t < n_tiers - 1:
            inside = np.zeros((nq, n_db), dtype=bool)
            r, c = np.nonzero(out >= 0)
            inside[r, out[r, c]] = True
            out_rows.inputs.append(length)  # the union has no repeats: all are scored next
    # The Combined score over the candidates entering the final tier (all of them: one tier).
    final_in = np.broadcast_to(np.arange(n_db), (nq, n_db)) if n_tiers == 1 else cands[n_tiers - 2]
    sizes = (final_in >= 0).sum(axis=1)
    mean_all = config.tier_score == "mean"
    for size in np.unique(sizes):
        if size == 0:
            continue  # no candidate: no answer (-1, NaN)
        group = np.flatnonzero(sizes == size)
        f = np.ascontiguousarray(final_in[group, :size])  # unions are packed at the front
        total: np.ndarray | None = None
        for t, (tier, w) in enumerate(zip(config.tiers, config.tier_weights, strict=True)):
            at = [np.take_along_axis(normed[t][m][group], f, axis=1) for m in tier.methods]
            value = np.mean(at, axis=0) if mean_all or t == n_tiers - 1 else np.fmax.reduce(at)
            part = _minmax_rows(np.ascontiguousarray(value), True) * float(w)
            total = part if total is None else total + part
        assert total is not None
        z = _zscore_rows(np.ascontiguousarray(total))
        j = _nan_argmax_rows(z)
        out_rows.match[group] = f[np.arange(len(group)), j]
        out_rows.quality[group] = z[np.arange(len(group)), j]
    return out_rows
