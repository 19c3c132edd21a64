"""The HMPF hierarchy: tiers narrowing the candidate list, scores fused across tiers.

Per query (spec §5.2-5.3, docs/spec/fusion.md):

1. Tier 1 scores the whole database with each of its methods (normalised over the database).
2. A non-final tier passes on the union of its methods' top-k; the next tier scores only
   those candidates, normalised over them.
3. The final tier averages its methods; its own top-k is reported (per-tier recall) but is
   not the answer.
4. The answer is the argmax of the z-scored Combined score over the candidates *entering* the
   final tier: earlier tiers contribute the max over their methods (or, with
   ``tier_score: mean``, their mean), the final tier its mean, each min-max normalised over
   those candidates and weighted (1, 0.75, 0.5 from the final tier backwards). The max z is
   the answer's quality.

Unlike the original, any number of tiers (one included: the candidates entering it are the
whole database) and of methods per tier is allowed, and a method may appear in several tiers.
Scores come from a ``score_fn(method_id, subset)`` callback so the same code runs on cached
features (evaluation) and on an index (service).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hmpf.config import HierarchyConfig
from hmpf.fusion import (
    Filled,
    Spread,
    combined_score,
    mean_of,
    minmax_normalise,
    nan_argmax,
    top_k,
    union,
    zscore,
)
from hmpf.methods import Method

__all__ = ["Hierarchy", "HierarchyResult", "ScoreFn", "TierResult", "entries_at", "feature_scorer"]

#: ``score_fn(method_id, subset)`` -> raw scores for ``subset`` (reference indices, in order),
#: or for the whole database when ``subset`` is None (an approximate tier 1: a
#: :class:`~hmpf.fusion.Filled` vector; ``np.asarray`` of it is the whole array).
ScoreFn = Callable[[str, np.ndarray | None], np.ndarray | Filled]


def feature_scorer(
    methods: Mapping[str, Method], query: Mapping[str, Any], references: Mapping[str, Any]
) -> ScoreFn:
    """A :data:`ScoreFn` for one query from in-memory features.

    Args:
        methods: method id -> instance.
        query: method id -> the query's feature.
        references: method id -> the stored reference set (``Method.stack``).

    Whole-database scores are remembered, so a method met again in a later tier costs a
    gather instead of a second comparison.
    """
    memo: dict[str, np.ndarray] = {}

    def score_fn(mid: str, subset: np.ndarray | None) -> np.ndarray:
        if mid in memo:
            return memo[mid] if subset is None else memo[mid][subset]
        raw = methods[mid].scores(query[mid], references[mid], subset)
        if subset is None:
            memo[mid] = raw
        return raw

    return score_fn


def entries_at(x: Mapping[str, np.ndarray], mid: str, at: np.ndarray | None) -> np.ndarray:
    """``x[mid][at]`` (``at`` None: ``x[mid]``) of a tier's scores, read from the entries of
    a :class:`~hmpf.fusion.Spread` without making its whole array."""
    if at is None:
        return x[mid]
    return x.at(mid, at) if isinstance(x, Spread) else x[mid][at]


@dataclass
class TierResult:
    """One tier of one query.

    Attributes:
        methods: method ids of the tier.
        inputs: reference indices the tier scored (``None``: the whole database). In faithful
            mode this list may contain duplicates.
        scores: per method, the (N,) normalised score (best = 1); off-input entries are 0
            (faithful) or NaN (default).
        candidates: the tier's output list: union of per-method top-k (non-final tiers) or the
            top-k of the averaged score (final tier).
        time_ms: wall time of the tier (scoring, normalisation, selection).
        raw: per method, the (N,) raw score before normalisation (NaN off input): what
            :class:`~hmpf.confidence.ReferenceProfile` compares in absolute terms. Empty
            where a result was built without it.
    """

    methods: list[str]
    inputs: np.ndarray | None
    scores: Mapping[str, np.ndarray]
    candidates: np.ndarray
    time_ms: float
    raw: Mapping[str, np.ndarray] = field(default_factory=dict)

    def mean_score(self, at: np.ndarray | None = None) -> np.ndarray:
        """(N,) mean over the tier's methods (the original's ``recall_top1_by_level`` input);
        with ``at``, just those entries (the same values).

        ``np.mean`` over the methods' stacked arrays, to the last bit, without the stack
        (:func:`~hmpf.fusion.mean_of`)."""
        return mean_of([entries_at(self.scores, m, at) for m in self.methods])

    def whole_mean(self) -> np.ndarray | Filled:
        """:meth:`mean_score` over the whole database; for an approximate tier 1 a
        :class:`~hmpf.fusion.Filled` vector of the same values (its entries and fill), so
        that a pass over the map can be one over its entries."""
        if (
            isinstance(self.scores, Spread)
            and not np.isnan([self.scores.fill[m] for m in self.methods]).any()
        ):
            return mean_of([self.scores.filled(m) for m in self.methods])
        return self.mean_score()

    def max_score(self, at: np.ndarray | None = None) -> np.ndarray:
        """(N,) element-wise max over methods, NaN ignored (MATLAB ``max``); with ``at``,
        just those entries (the same values)."""
        stack = np.stack([entries_at(self.scores, m, at) for m in self.methods])
        out = np.full(stack.shape[1], np.nan)
        has = ~np.isnan(stack).all(axis=0)
        out[has] = np.nanmax(stack[:, has], axis=0)
        return out


@dataclass
class HierarchyResult:
    """The answer for one query and the evidence behind it.

    ``matched_rows`` is set by whoever scored places rather than images (an index version
    with several experiences per place, :meth:`hmpf.index.reader.IndexReader.matched_rows`):
    per place of the whole map (its id, also under a GPS prior), the stored row (experience)
    that matched it, -1 where none was scored; None: every place is one image.

    ``sketch`` is set by whoever ran the query for a sequence filter that weighs motion:
    the frame's :class:`~hmpf.sequence.MotionSketch` (None: not sketched), which
    :meth:`~hmpf.sequence.Evidence.from_result` hands on to the filter.
    """

    match: int
    quality: float
    final_candidates: np.ndarray
    combined: np.ndarray  # z-scores over final_candidates
    tiers: list[TierResult] = field(default_factory=list)
    fusion_ms: float = 0.0
    matched_rows: np.ndarray | None = field(default=None, repr=False)
    sketch: np.ndarray | None = field(default=None, repr=False)

    def ranking(self) -> np.ndarray:
        """Final candidates ranked by Combined z-score, duplicates removed (an extension)."""
        z = np.where(np.isnan(self.combined), -np.inf, self.combined)
        order = np.argsort(-z, kind="stable")
        return union([self.final_candidates[order]], faithful=False)


def _tier_scores(
    n_db: int, sel: np.ndarray | None, scores: dict[str, Any], filled: bool
) -> Mapping[str, np.ndarray]:
    """A tier's scores as :class:`TierResult` holds them: entries at the inputs of a later
    tier, an approximate tier 1's entries and fills, whole arrays otherwise."""
    if filled and scores:
        return Spread.of_filled(n_db, scores)
    scores = {m: np.asarray(x) if isinstance(x, Filled) else x for m, x in scores.items()}
    return Spread(n_db, sel, scores) if sel is not None else scores


class Hierarchy:
    """Runs a :class:`HierarchyConfig` over one query's scores."""

    def __init__(self, config: HierarchyConfig, methods: Mapping[str, Method]) -> None:
        missing = [m for m in config.method_ids if m not in methods]
        if missing:
            raise ValueError(f"no method instance for {missing}")
        self.config = config
        self.methods = dict(methods)

    def run(self, score_fn: ScoreFn, n_db: int) -> HierarchyResult:
        """Run every tier for one query against a database of ``n_db`` references."""
        cfg = self.config
        faithful = cfg.faithful
        off = 0.0 if faithful else np.nan
        tiers: list[TierResult] = []
        inputs: np.ndarray | None = None
        n_tiers = len(cfg.tiers)
        for t, tier in enumerate(cfg.tiers):
            start = time.perf_counter()
            scores: dict[str, np.ndarray | Filled] = {}
            raws: dict[str, np.ndarray | Filled] = {}
            if inputs is not None:
                uniq, inverse = np.unique(inputs, return_inverse=True)
            for mid in tier.methods:
                method = self.methods[mid]
                if inputs is None:
                    # An approximate tier 1 (a Filled vector) stays entries and a fill, but
                    # for the final tier (whole arrays: every reference enters the fusion) and
                    # in faithful mode (the original's arrays).
                    raw = score_fn(mid, None)
                    if not isinstance(raw, Filled) or faithful or t == n_tiers - 1:
                        raw = np.asarray(raw, dtype=np.float64)
                    scores[mid] = minmax_normalise(raw, method.higher_is_better, faithful=faithful)
                    raws[mid] = raw
                else:
                    raw_u = np.asarray(score_fn(mid, uniq), dtype=np.float64)
                    # Normalise over the listed entries (duplicates included, as the original).
                    norm = minmax_normalise(
                        raw_u[inverse], method.higher_is_better, faithful=faithful
                    )
                    entries = np.empty(len(uniq))
                    entries[inverse] = norm  # the same value at every duplicate
                    scores[mid], raws[mid] = entries, raw_u
            # A later tier covers only its inputs: outside faithful mode the rest is NaN,
            # which selection skips, so its scores stay entries at the inputs (ascending:
            # ties still go to the lower index). Faithful mode's rest is 0, and can be
            # selected: whole arrays, as the original.
            sel = None if inputs is None or faithful else uniq
            at = dict(scores) if inputs is None or not faithful else {}
            filled = inputs is None and all(isinstance(x, Filled) for x in scores.values())
            if inputs is not None and faithful:
                for mid in tier.methods:
                    spread = np.full(n_db, off)
                    spread[uniq] = scores[mid]
                    at[mid] = spread
                    whole = np.full(n_db, np.nan)
                    whole[uniq] = raws[mid]
                    raws[mid] = whole
                scores = at
            if t < n_tiers - 1:
                picks = [top_k(at[m], tier.k) for m in tier.methods]
            else:
                picks = [top_k(np.mean([at[m] for m in tier.methods], axis=0), tier.k)]
            if sel is not None:
                picks = [sel[p] for p in picks]
            cands = union(picks, faithful=faithful) if t < n_tiers - 1 else picks[0]
            tiers.append(
                TierResult(
                    list(tier.methods),
                    inputs,
                    _tier_scores(n_db, sel, scores, filled),
                    cands,
                    (time.perf_counter() - start) * 1e3,
                    _tier_scores(n_db, sel, raws, filled),
                )
            )
            inputs = cands
        start = time.perf_counter()
        final_in = tiers[-1].inputs
        F = np.arange(n_db, dtype=np.int64) if final_in is None else final_in
        mean_all = cfg.tier_score == "mean"
        values = [
            tr.mean_score(F) if mean_all or t == n_tiers - 1 else tr.max_score(F)
            for t, tr in enumerate(tiers)
        ]
        if len(F) == 0:
            return HierarchyResult(-1, float("nan"), F, np.zeros(0), tiers)
        z = zscore(combined_score(values, cfg.tier_weights, faithful=faithful))
        j = nan_argmax(z)
        return HierarchyResult(
            match=int(F[j]),
            quality=float(z[j]),
            final_candidates=F,
            combined=z,
            tiers=tiers,
            fusion_ms=(time.perf_counter() - start) * 1e3,
        )
