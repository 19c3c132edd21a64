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
them: it runs per query); nothing is timed (``tier_ms`` and ``fusion_ms`` are NaN).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from hmpf.config import HierarchyConfig
from hmpf.evaluation.metrics import HierarchyOutcome
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
    n = cat.shape[1]
    earlier = np.triu(np.ones((n, n), dtype=bool), k=1)  # [i, j]: i before j
    repeat = ((cat[:, :, None] == cat[:, None, :]) & earlier).any(axis=1)
    keep = (cat >= 0) & ~repeat
    order = np.argsort(~keep, axis=1, kind="stable")
    out = np.take_along_axis(cat, order, axis=1)
    kept = np.take_along_axis(keep, order, axis=1)
    out[~kept] = -1
    return out, keep.sum(axis=1)


def _gather(x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``x[q, idx[q]]`` per row, NaN where ``idx`` is -1."""
    out = np.take_along_axis(x, np.maximum(idx, 0), axis=1)
    out[idx < 0] = np.nan
    return out


def _nan_argmax_rows(x: np.ndarray) -> np.ndarray:
    """:func:`hmpf.fusion.nan_argmax` of every row (first maximum, NaN skipped; all NaN: 0)."""
    return np.argmax(np.where(np.isnan(x), -np.inf, x), axis=1)


def _zscore_rows(v: np.ndarray) -> np.ndarray:
    """:func:`hmpf.fusion.zscore` of every row of a C-contiguous (Q, L) array."""
    q, n = v.shape
    if n == 1:
        return np.where(np.isnan(v), np.nan, 0.0)
    mean = v.mean(axis=1, keepdims=True)
    sd = v.std(axis=1, ddof=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (v - mean) / sd
    out[(sd == 0)[:, 0]] = 0.0
    out[np.isnan(v).any(axis=1)] = np.nan
    return out


def batch_outcome(
    config: HierarchyConfig,
    methods: Mapping[str, Method],
    scores: Mapping[str, np.ndarray],
    gt: np.ndarray,
) -> HierarchyOutcome | None:
    """``config`` over every query of a bank: ``outcome_of`` of the per-query results.

    Args:
        config: the hierarchy; None is returned for faithful mode (run it per query).
        methods: method id -> instance (only ``higher_is_better`` is read).
        scores: method id -> (Q, N) raw scores of every query against every reference.
        gt: (Q, N) ground truth.
    """
    if config.faithful:
        return None
    gt = np.asarray(gt, dtype=bool)
    nq, n_db = gt.shape
    rows = np.arange(nq)[:, None]
    n_tiers = len(config.tiers)
    normed: list[dict[str, np.ndarray]] = []
    cands: list[np.ndarray] = []
    top1, recall, inputs_n, cands_n = [], [], [], []
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
        top1.append(float(np.mean(gt[np.arange(nq), _nan_argmax_rows(mean)])))
        recall.append(float(np.mean((gt[rows, np.maximum(out, 0)] & (out >= 0)).any(axis=1))))
        inputs_n.append(float(n_db) if inside is None else float(np.mean(inside.sum(axis=1))))
        cands_n.append(float(np.mean(length)))
        inside = np.zeros((nq, n_db), dtype=bool)
        r, c = np.nonzero(out >= 0)
        inside[r, out[r, c]] = True
    # The Combined score over the candidates entering the final tier (all of them: one tier).
    final_in = np.broadcast_to(np.arange(n_db), (nq, n_db)) if n_tiers == 1 else cands[n_tiers - 2]
    sizes = (final_in >= 0).sum(axis=1)
    match = np.full(nq, -1, dtype=np.int64)
    quality = np.full(nq, np.nan)
    mean_all = config.tier_score == "mean"
    for size in np.unique(sizes):
        if size == 0:
            continue  # no candidate: no answer (-1, NaN)
        group = np.flatnonzero(sizes == size)
        f = np.ascontiguousarray(final_in[group, :size])  # unions are packed at the front
        total: np.ndarray | None = None
        for t, (tier, w) in enumerate(zip(config.tiers, config.tier_weights, strict=True)):
            at = [_gather(normed[t][m][group], f) for m in tier.methods]
            value = np.mean(at, axis=0) if mean_all or t == n_tiers - 1 else np.fmax.reduce(at)
            part = _minmax_rows(np.ascontiguousarray(value), True) * float(w)
            total = part if total is None else total + part
        assert total is not None
        z = _zscore_rows(np.ascontiguousarray(total))
        j = _nan_argmax_rows(z)
        match[group] = f[np.arange(len(group)), j]
        quality[group] = z[np.arange(len(group)), j]
    correct = np.zeros(nq, dtype=bool)
    ok = match >= 0
    correct[ok] = gt[np.flatnonzero(ok), match[ok]]
    nan_ms = [float("nan")] * n_tiers
    return HierarchyOutcome(
        match, quality, correct, top1, recall, inputs_n, cands_n, nan_ms, float("nan")
    )
