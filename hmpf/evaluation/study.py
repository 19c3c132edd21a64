"""Many hierarchies on one route (layer 3 of :mod:`hmpf.evaluation`).

Train/test splits, score banks and a cost model.

A :class:`ScoreBank` holds, for one split of a route, every pool method's raw score of every
query against every reference (features come through the descriptor cache, so a second run
extracts nothing). Any hierarchy over those methods then runs on the matrices: per query
through the same :class:`~hmpf.hierarchy.Hierarchy` code as evaluation and the service
(:meth:`ScoreBank.results`), or for every query at once with the same floats
(:meth:`ScoreBank.run`, :mod:`hmpf.evaluation.batch`): thousands of hierarchies cost seconds,
not re-extraction.

:class:`CostModel` turns measured component times (single-image extraction: the pass shared by
a group of methods and each method's own work; per-method matching as a function of the number
of references scored) into a per-query time for any hierarchy, so a calibration search can
respect a time budget; the chosen hierarchy's time is then measured end to end
(:func:`measure_query_ms`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.confidence import ReferenceProfile
from hmpf.config import HierarchyConfig, TierConfig, build_methods
from hmpf.errors import ConfigError, DatasetError
from hmpf.evaluation import SPLITS
from hmpf.evaluation.batch import batch_outcome
from hmpf.evaluation.data import EvalData, prepare
from hmpf.evaluation.metrics import HierarchyOutcome, outcome_of, recall_at_n, run_queries
from hmpf.evaluation.sequence import (
    motion_sketches,
    sequence_report,
    sketch_results,
    tune_sequence,
)
from hmpf.features import FeatureCache, extract_query
from hmpf.hierarchy import Hierarchy, HierarchyResult, ScoreFn, feature_scorer
from hmpf.imageio import load_image
from hmpf.methods import Method
from hmpf.methods.base import method_groups
from hmpf.runtime import compute_threads, set_compute_threads
from hmpf.sequence import FilterParams, RouteMap

__all__ = [
    "CostModel",
    "ScoreBank",
    "check_compatible",
    "derive_config",
    "measure_costs",
    "measure_query_ms",
    "split_data",
]


# -- splits ----------------------------------------------------------------------------------


def split_data(
    data: EvalData, train_fraction: float = 0.5, *, scheme: str = "blocks", block: int = 20
) -> tuple[EvalData, EvalData]:
    """Split a route into a training and a test part, by stretches of the route.

    ``halves``: the first ``train_fraction`` of the references and of the queries (in file
    order, i.e. along the route) train, the rest tests, as the paper splits Nordland and
    Berlin into earlier and later stretches. ``blocks``: the route is cut into stretches of
    ``block`` frames that alternate between the parts (``train_fraction`` must be 0.5), so
    both parts see every kind of place on the route while sharing none. Either way each
    part's ground truth is the matching block of the full one, and a reference belongs to
    exactly one part; the queries and references must be frame-aligned for ``blocks``.
    """
    if scheme not in SPLITS:
        raise DatasetError(f"unknown split {scheme!r} (choose from {', '.join(SPLITS)})")
    if not 0.0 < train_fraction < 1.0:
        raise DatasetError("train_fraction must be between 0 and 1 (exclusive)")
    nr, nq = len(data.reference), len(data.query)
    if scheme == "halves":
        cr, cq = round(nr * train_fraction), round(nq * train_fraction)
        r_parts = (np.arange(cr), np.arange(cr, nr))
        q_parts = (np.arange(cq), np.arange(cq, nq))
    else:
        if train_fraction != 0.5:
            raise DatasetError("the blocks split alternates stretches: train_fraction must be 0.5")
        if block < 1:
            raise DatasetError("block must be >= 1 frame")
        r_blk, q_blk = (np.arange(nr) // block) % 2, (np.arange(nq) // block) % 2
        r_parts = (np.flatnonzero(r_blk == 0), np.flatnonzero(r_blk == 1))
        q_parts = (np.flatnonzero(q_blk == 0), np.flatnonzero(q_blk == 1))
    if min(len(x) for x in (*r_parts, *q_parts)) < 2:
        raise DatasetError(f"too few images to split ({nr} references, {nq} queries)")
    gt = np.asarray(data.gt, bool)
    parts = [
        EvalData(
            [data.reference[i] for i in r],
            [data.query[i] for i in q],
            gt[np.ix_(q, r)],
            data.ground_truth,
        )
        for r, q in zip(r_parts, q_parts, strict=True)
    ]
    return parts[0], parts[1]


# -- the pool of methods and configs derived from it -----------------------------------------


def derive_config(
    pool: HierarchyConfig,
    tiers: Sequence[tuple[Sequence[str], int]],
    weights: Sequence[float] | None = None,
    *,
    name: str = "derived",
    description: str = "",
    mode: str | None = None,
) -> HierarchyConfig:
    """A hierarchy over the pool's methods (their parameters copied from the pool config).

    Args:
        tiers: (method ids, k) per tier, tier 1 first.
        weights: tier weights (tier 1 first), or None for the defaults.
    """
    used = {m for ms, _ in tiers for m in ms}
    unknown = used - set(pool.method_ids)
    if unknown:
        raise ConfigError(f"methods not in the pool: {', '.join(sorted(unknown))}")
    return HierarchyConfig(
        name=name,
        description=description,
        mode=mode or pool.mode,  # type: ignore[arg-type]
        tier_score=pool.tier_score,
        methods={m: dict(p) for m, p in pool.methods.items() if m in used},
        tiers=[TierConfig(methods=list(ms), k=int(k)) for ms, k in tiers],
        weights=list(weights) if weights is not None else None,
    )


def check_compatible(config: HierarchyConfig, pool: HierarchyConfig) -> None:
    """``config`` may run on the pool's score banks: same method ids with the same settings."""
    for mid in config.method_ids:
        if mid not in pool.method_ids:
            raise ConfigError(f"method {mid!r} of {config.name!r} is not in the pool {pool.name!r}")
        if config.method_spec(mid) != pool.method_spec(mid):
            raise ConfigError(
                f"method {mid!r} has other settings in {config.name!r} "
                f"({config.method_spec(mid)}) than in the pool {pool.name!r} "
                f"({pool.method_spec(mid)})"
            )


# -- score banks -----------------------------------------------------------------------------


@dataclass
class ScoreBank:
    """Every pool method's raw scores for one split (queries x references).

    Attributes:
        methods: method id -> fitted instance (fitted on this split's references).
        scores: method id -> (nq, nd) raw scores.
        gt: (nq, nd) ground truth.
        data: the split.
        features: method id -> (reference set, per-query features), for timing real runs.
        motion_features: the global methods' (reference matrix, per-query features) of a
            bank without ``features`` (:meth:`subset`), for the frames' motion sketches.
        map_prior: the map's prior (:func:`hmpf.evaluation.auto.map_prior`'s ``map_prior``,
            what an index version stores), given to :meth:`profile` and so to every
            answer's features; None: unknown. :meth:`subset` and :meth:`rows` keep it.
    """

    methods: dict[str, Method]
    scores: dict[str, np.ndarray]
    gt: np.ndarray
    data: EvalData
    features: dict[str, tuple[Any, list[Any]]] = field(default_factory=dict)
    motion_features: dict[str, tuple[Any, list[Any]]] = field(default_factory=dict)
    map_prior: float | None = None

    @classmethod
    def build(
        cls,
        pool: HierarchyConfig,
        data: EvalData,
        *,
        cache: FeatureCache | None = None,
        workers: int | None = None,
        progress: bool = False,
    ) -> ScoreBank:
        """Extract (or load from the cache) every pool method's features and score them all."""
        prep = prepare(build_methods(pool), data, cache=cache, workers=workers, progress=progress)
        scores: dict[str, np.ndarray] = {}
        feats: dict[str, tuple[Any, list[Any]]] = {}
        for mid, m in prep.methods.items():
            db, qs = prep.db[mid], prep.queries[mid]
            # Per query with subset None: exactly what the hierarchy's scorer computes.
            scores[mid] = np.stack([np.asarray(m.scores(q, db), np.float64) for q in qs])
            feats[mid] = (db, qs)
        return cls(prep.methods, scores, np.asarray(data.gt, bool), data, feats)

    @property
    def n_query(self) -> int:
        return int(self.gt.shape[0])

    @property
    def n_db(self) -> int:
        return int(self.gt.shape[1])

    def subset(self, keep: np.ndarray) -> ScoreBank:
        """The bank over the references ``keep`` only (a map with the others removed; the
        methods stay fitted as they were, no features for timing; the global methods'
        matrices cut to ``keep`` for the frames' motion sketches)."""
        k = np.asarray(keep, dtype=np.int64)
        scores = {m: s[:, k] for m, s in self.scores.items()}
        motion = {
            m: (db[k], qs)
            for m, (db, qs) in (self.features or self.motion_features).items()
            if isinstance(db, np.ndarray)
        }
        return ScoreBank(self.methods, scores, self.gt[:, k], self.data, {}, motion, self.map_prior)

    def rows(self, keep: np.ndarray) -> ScoreBank:
        """The bank of the queries ``keep`` only (the same map and fitted methods)."""
        k = np.asarray(keep, dtype=np.int64)
        scores = {m: s[k] for m, s in self.scores.items()}
        data = replace(self.data, query=[self.data.query[i] for i in k], gt=self.data.gt[k])
        feats = {m: (db, [qs[i] for i in k]) for m, (db, qs) in self.features.items()}
        motion = {m: (db, [qs[i] for i in k]) for m, (db, qs) in self.motion_features.items()}
        return ScoreBank(self.methods, scores, self.gt[k], data, feats, motion, self.map_prior)

    def sketches(self, config: HierarchyConfig) -> list[np.ndarray] | None:
        """Every query's motion sketch for ``config``'s sequence filter
        (:func:`~hmpf.evaluation.sequence.motion_sketches`; None when it weighs no motion or
        the bank holds no features of the method sketched)."""
        if not config.sequence_params().motion:
            return None
        source = self.features or self.motion_features
        db = {m: f[0] for m, f in source.items()}
        qs = {m: f[1] for m, f in source.items()}
        routes = RouteMap.from_metadata(self.n_db)
        return motion_sketches(self.methods, config.tiers[0].methods, db, qs, routes)

    def profile(self, config: HierarchyConfig) -> ReferenceProfile:
        """The :class:`~hmpf.confidence.ReferenceProfile` of this part's references for
        ``config``'s tier-1 methods (one route, file order), with the bank's
        :attr:`map_prior`."""
        db = {m: f[0] for m, f in self.features.items()}
        tier1 = config.tiers[0].methods
        prof = ReferenceProfile.build(self.methods, db, tier1, RouteMap.from_metadata(self.n_db))
        return replace(prof, map_prior=self.map_prior)

    def scorer(self, qi: int) -> ScoreFn:
        """A :data:`ScoreFn` for query ``qi`` gathering from the matrices."""
        rows = {m: s[qi] for m, s in self.scores.items()}

        def score_fn(mid: str, subset: np.ndarray | None) -> np.ndarray:
            row = rows[mid]
            return row if subset is None else row[subset]

        return score_fn

    def results(self, config: HierarchyConfig) -> list[HierarchyResult]:
        """``config``'s result for every query of the bank, in query order."""
        hier = Hierarchy(config, {m: self.methods[m] for m in config.method_ids})
        scorers = (self.scorer(q) for q in range(self.n_query))
        results, _ = run_queries(hier, scorers, self.n_db)
        sketch_results(results, self.sketches(config))  # a filter that weighs motion reads them
        return results

    def run(self, config: HierarchyConfig) -> HierarchyOutcome:
        """Run ``config`` for every query of the bank: the figures of :meth:`results`,
        computed on the whole matrices at once (:func:`~hmpf.evaluation.batch.batch_outcome`,
        the same floats, not timed) unless the mode is faithful."""
        fast = batch_outcome(config, self.methods, self.scores, self.gt)
        return fast if fast is not None else outcome_of(self.results(config), self.gt, self.n_db)

    def sequence(
        self, config: HierarchyConfig, params: FilterParams, *, seed: int = 0
    ) -> dict[str, Any]:
        """Sequence-mode figures of ``config`` on this part, its queries driven in order
        along its references (one route, file order)."""
        routes = RouteMap.from_metadata(self.n_db)
        return sequence_report(self.results(config), self.gt, routes, params, seed=seed)

    def tune_sequence(
        self, config: HierarchyConfig, *, target_precision: float = 0.99, seed: int = 0
    ) -> tuple[FilterParams, dict[str, Any]]:
        """The sequence filter's settings for ``config`` chosen on this (training) part."""
        return tune_sequence(
            [(self.results(config), self.gt, RouteMap.from_metadata(self.n_db))],
            base=config.sequence_params(),
            target_precision=target_precision,
            seed=seed,
        )

    def single_correct(self, mid: str) -> np.ndarray:
        """(Q,) whether one method alone ranks a correct reference first (ties: lower index)."""
        raw = self.scores[mid]
        key = -raw if self.methods[mid].higher_is_better else raw
        best = np.argmin(np.where(np.isnan(key), np.inf, key), axis=1)  # as recall_at_n
        return self.gt[np.arange(self.n_query), best]

    def single_recall(self, mid: str, ns: Sequence[int]) -> dict[int, float]:
        """recall@N of one method alone over the whole database."""
        return recall_at_n(self.scores[mid], self.gt, ns, self.methods[mid].higher_is_better)


# -- timing ----------------------------------------------------------------------------------


@dataclass
class CostModel:
    """Per-query time of a hierarchy from measured parts (ms, one compute thread).

    Attributes:
        units: extraction unit -> ms: ``forward:<g>`` the pass shared by a group of methods
            (a CNN forward pass), ``head:<id>`` a grouped method's own work, ``extract:<id>``
            a method extracted alone.
        method_units: method id -> the units its extraction needs.
        match: method id -> (a, b): scoring n references costs ``a + b * n`` ms.
        fusion_ms: normalisation, selection and fusion per tier.
        n_db: database size the tier-1 cost is charged for.
        threads: compute threads during the measurement.
    """

    units: dict[str, float]
    method_units: dict[str, list[str]]
    match: dict[str, tuple[float, float]]
    fusion_ms: float
    n_db: int
    threads: int = 1

    def extract_ms(self, method_ids: Sequence[str]) -> float:
        needed = {u for m in method_ids for u in self.method_units[m]}
        return float(sum(self.units[u] for u in needed))

    def match_ms(self, mid: str, n: float) -> float:
        a, b = self.match[mid]
        return a + b * n

    def query_ms(
        self, config: HierarchyConfig, mean_inputs: Sequence[float] | None = None
    ) -> float:
        """Extraction + matching + fusion of one query.

        ``mean_inputs`` gives the references each tier scores (tier 1: the database); without
        it, later tiers are charged their upper bound (methods x k of the tier before). A
        method already scored against the whole database is free in later tiers (the scorer
        remembers it).
        """
        total = self.extract_ms(config.method_ids)
        full: set[str] = set()
        prev_bound = float(self.n_db)
        for t, tier in enumerate(config.tiers):
            if t == 0:
                n = float(self.n_db)
            elif mean_inputs is not None:
                n = float(mean_inputs[t])
            else:
                n = prev_bound
            for mid in tier.methods:
                if mid in full:
                    continue
                total += self.match_ms(mid, n)
                if t == 0:
                    full.add(mid)
            prev_bound = float(min(self.n_db, len(tier.methods) * tier.k))
            total += self.fusion_ms
        return total

    def to_dict(self) -> dict[str, Any]:
        return {
            "units_ms": self.units,
            "method_units": self.method_units,
            "match_ms": {m: {"a": a, "b_per_ref": b} for m, (a, b) in self.match.items()},
            "fusion_ms_per_tier": self.fusion_ms,
            "n_db": self.n_db,
            "threads": self.threads,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CostModel:
        """Inverse of :meth:`to_dict` (e.g. the ``costs`` of a calibration report)."""
        try:
            return cls(
                units={str(k): float(v) for k, v in data["units_ms"].items()},
                method_units={str(k): list(v) for k, v in data["method_units"].items()},
                match={
                    str(m): (float(ab["a"]), float(ab["b_per_ref"]))
                    for m, ab in data["match_ms"].items()
                },
                fusion_ms=float(data["fusion_ms_per_tier"]),
                n_db=int(data["n_db"]),
                threads=int(data.get("threads", 1)),
            )
        except (KeyError, TypeError, AttributeError, ValueError) as exc:
            raise ConfigError(
                f"not a cost model (as a calibration report's 'costs'): {exc!r}"
            ) from exc


def measure_costs(
    bank: ScoreBank, *, images: int = 5, n_db: int | None = None, threads: int = 1
) -> CostModel:
    """Measure extraction and matching costs on the bank's own images and features.

    Extraction: ``images`` query images decoded, then each group of methods sharing one pass
    per image (:func:`~hmpf.methods.base.method_groups`) extracted one image at a time by its
    declared :meth:`~hmpf.methods.base.Method.extract_group` after a warm-up; medians of the
    times it reports. A group's shared pass (a CNN forward pass) is one unit and each member's
    own work another; a method extracted alone is one unit (its shared and own time).
    Matching: each method scoring 10 references and the whole database, medians over the
    same queries, fitted as ``a + b * n``. Everything on ``threads`` compute threads.
    """
    previous = compute_threads()
    set_compute_threads(threads)
    try:
        decoded = [load_image(p) for p in bank.data.query[: max(1, images)]]
        units: dict[str, float] = {}
        method_units: dict[str, list[str]] = {}
        groups = method_groups(bank.methods)
        shared = [g for g in groups if next(iter(g.values())).group_key() is not None]
        alone = [g for g in groups if next(iter(g.values())).group_key() is None]
        # Shared groups first, then methods alone (the order calibration reports were in).
        for g, group in enumerate(shared):
            pass_ms, own = _extraction_ms(group, decoded)
            key = f"forward:{g}"
            units[key] = float(np.median(pass_ms))
            for mid in group:
                units[f"head:{mid}"] = float(np.median(own[mid]))
                method_units[mid] = [key, f"head:{mid}"]
        for group in alone:
            pass_ms, own = _extraction_ms(group, decoded)
            for mid in group:
                units[f"extract:{mid}"] = float(
                    np.median([s + o for s, o in zip(pass_ms, own[mid], strict=True)])
                )
                method_units[mid] = [f"extract:{mid}"]
        match: dict[str, tuple[float, float]] = {}
        nd = bank.n_db
        small = np.arange(min(10, nd), dtype=np.int64)
        for mid, method in bank.methods.items():
            db, qs = bank.features[mid]
            sample = qs[: max(1, images)]
            method.scores(sample[0], db, small)  # warm-up
            t_small = _median_ms(method.scores, [(q, db, small) for q in sample])
            t_full = _median_ms(method.scores, [(q, db, None) for q in sample])
            b = max(0.0, (t_full - t_small) / max(1, nd - len(small)))
            match[mid] = (max(0.0, t_small - b * len(small)), b)
        # Normalisation, selection and fusion: a two-tier run of the cheapest method on the
        # gathered scores, per tier.
        cheapest = min(match, key=lambda m: match[m][1])
        cfg = HierarchyConfig(
            tiers=[TierConfig(methods=[cheapest], k=10), TierConfig(methods=[cheapest], k=1)]
        )
        hier = Hierarchy(cfg, {cheapest: bank.methods[cheapest]})
        nq = min(20, bank.n_query)
        runs = [
            _time_ms(lambda: [hier.run(bank.scorer(q), nd) for q in range(nq)]) for _ in range(3)
        ]
        fusion_ms = float(np.median(runs)) / nq / 2
    finally:
        set_compute_threads(previous)
    return CostModel(units, method_units, match, fusion_ms, n_db or nd, threads)


def _extraction_ms(
    group: dict[str, Method], decoded: Sequence[np.ndarray]
) -> tuple[list[float], dict[str, list[float]]]:
    """Shared and own times (ms) of ``group`` extracting each image alone, after a warm-up
    on the first: ``(shared per image, {method id: own per image})``."""
    extract_group = type(next(iter(group.values()))).extract_group
    extract_group(group, decoded[:1])  # warm-up
    shared: list[float] = []
    own: dict[str, list[float]] = {mid: [] for mid in group}
    for img in decoded:
        out = extract_group(group, [img])
        shared.extend(out.shared_ms)
        for mid in group:
            own[mid].extend(out.own_ms[mid])
    return shared, own


def _median_ms(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]]) -> float:
    """Median wall time (ms) of ``fn(*args)`` over ``calls``."""
    return float(np.median([_time_ms(lambda a=a: fn(*a)) for a in calls]))


def _time_ms(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def measure_query_ms(
    config: HierarchyConfig,
    bank: ScoreBank,
    *,
    images: int = 10,
    threads: int = 1,
) -> dict[str, float]:
    """End-to-end time per query of ``config``: decode + extraction + hierarchy, measured.

    Runs the real methods (not the bank's matrices) on the bank's first ``images`` queries,
    one at a time on ``threads`` compute threads, after one warm-up; medians in ms.
    """
    methods = {m: bank.methods[m] for m in config.method_ids}
    refs = {m: bank.features[m][0] for m in methods}
    hier = Hierarchy(config, methods)
    previous = compute_threads()
    set_compute_threads(threads)  # OpenCV here, torch at each forward pass
    ext, match, total = [], [], []
    try:
        paths: list[Path] = list(bank.data.query[: max(1, images)])
        for i, p in enumerate([paths[0], *paths]):
            t0 = time.perf_counter()
            img = load_image(p)
            feats = extract_query(methods, img)
            t1 = time.perf_counter()
            hier.run(feature_scorer(methods, feats, refs), bank.n_db)
            t2 = time.perf_counter()
            if i == 0:
                continue  # warm-up
            ext.append((t1 - t0) * 1e3)
            match.append((t2 - t1) * 1e3)
            total.append((t2 - t0) * 1e3)
    finally:
        set_compute_threads(previous)
    return {
        "total_ms": float(np.median(total)),
        "extract_ms": float(np.median(ext)),
        "hierarchy_ms": float(np.median(match)),
        "images": len(total),
        "threads": threads,
    }
