"""One hierarchy against ground truth (layer 4 of :mod:`hmpf.evaluation`).

Reports what the paper reports (``recall_final``, ``recall_by_level``,
``recall_top1_by_level``, the precision-recall curve over the quality score; spec §6,
docs/spec/evaluation.md) and more: recall@N of every method alone, flat-fusion recall, and time per
stage.

Every evaluation starts from :func:`~hmpf.evaluation.data.prepare` (fit -> extract -> stack),
runs the hierarchy per query (:func:`~hmpf.evaluation.metrics.run_queries`), summarises the
answers with :func:`~hmpf.evaluation.metrics.outcome_of` and reports the
tiers with :func:`tier_rows` / :func:`format_tier_table`: on a route (:func:`evaluate`), on a
built index through the service's own scorer (:func:`evaluate_index`) and, for many
hierarchies on precomputed scores, in :class:`hmpf.evaluation.study.ScoreBank`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hmpf.acceptance import Policy
from hmpf.confidence import ReferenceProfile
from hmpf.config import HierarchyConfig, build_methods
from hmpf.evaluation.acceptance import apply_acceptance, sequence_answers, single_answers
from hmpf.evaluation.auto import map_prior_or_why
from hmpf.evaluation.data import EvalData, Prepared, prepare
from hmpf.evaluation.metrics import (
    RECALL_NS,
    HierarchyOutcome,
    median,
    outcome_of,
    pr_curve,
    recall_at_n,
    run_queries,
)
from hmpf.evaluation.sequence import (
    format_off_map_report,
    format_sequence_report,
    motion_sketches,
    off_map_report,
    sequence_report,
    sketch_results,
)
from hmpf.features import FeatureCache, extract_images
from hmpf.fusion import flat_fusion, nan_argmax, zscore
from hmpf.hierarchy import Hierarchy, HierarchyResult, feature_scorer
from hmpf.methods import Method
from hmpf.sequence import RouteMap

if TYPE_CHECKING:
    from hmpf.index.reader import IndexReader

__all__ = [
    "RECALL_NS",
    "EvalData",
    "HierarchyOutcome",
    "Prepared",
    "evaluate",
    "evaluate_index",
    "format_index_report",
    "format_report",
    "format_tier_table",
    "outcome_of",
    "pr_curve",
    "prepare",
    "recall_at_n",
    "run_queries",
    "tier_rows",
]


def tier_rows(config: HierarchyConfig, outcome: HierarchyOutcome) -> list[dict[str, Any]]:
    """The report's per-tier table: methods, k, candidate recall, top-1 recall, size, time."""
    return [
        {
            "methods": list(tier.methods),
            "k": tier.k,
            "recall": outcome.tier_recall[t],
            "top1_recall": outcome.tier_top1[t],
            "mean_candidates_out": outcome.mean_candidates[t],
            "ms_per_query": outcome.tier_ms[t],
        }
        for t, tier in enumerate(config.tiers)
    ]


def format_tier_table(tiers: Sequence[dict[str, Any]]) -> list[str]:
    """:func:`tier_rows` as text lines, a header first."""
    lines = ["tier  methods              k   cand.recall  top1.recall  ms/query"]
    for i, t in enumerate(tiers, start=1):
        lines.append(
            f"{i:<5} {'+'.join(t['methods']):<20} {t['k']:<4} {t['recall']:11.3f}"
            f"  {t['top1_recall']:11.3f}  {t['ms_per_query']:8.2f}"
        )
    return lines


# -- evaluation on a route ---------------------------------------------------------------------


def _full_scores(method: Method, queries: Any, db: Any) -> np.ndarray:
    """(nq, nd) raw scores of every query against the whole database."""
    if method.kind == "global":
        return method.pairwise(queries, db)  # type: ignore[attr-defined]
    return np.stack([method.scores(q, db) for q in queries])


def _method_curves(
    prep: Prepared, gt: np.ndarray, skip_curves: Sequence[str]
) -> tuple[dict[str, Any], dict[str, np.ndarray], float]:
    """Every method alone over the whole database: (report entries, score matrices, seconds)."""
    full: dict[str, np.ndarray] = {}
    report: dict[str, Any] = {}
    n_q = len(gt)
    t0 = time.perf_counter()
    for mid, m in prep.methods.items():
        entry: dict[str, Any] = {
            "type": type(m).name,
            "kind": m.kind,
            "higher_is_better": m.higher_is_better,
            "extract_ms_per_image": median(np.concatenate([prep.ref.ms[mid], prep.qry.ms[mid]])),
        }
        if mid not in skip_curves:
            ts = time.perf_counter()
            full[mid] = _full_scores(m, m.stack(prep.queries[mid]), prep.db[mid])
            entry["match_ms_per_query_full_db"] = (time.perf_counter() - ts) * 1e3 / max(1, n_q)
            recall = recall_at_n(full[mid], gt, RECALL_NS, m.higher_is_better)
            entry["recall_at"] = {str(k): v for k, v in recall.items()}
        report[mid] = entry
    return report, full, time.perf_counter() - t0


def _flat_baseline(
    full: dict[str, np.ndarray],
    methods: dict[str, Method],
    flat_ids: Sequence[str],
    faithful: bool,
    n_q: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Flat fusion of ``flat_ids`` for ``n_q`` queries: (answers, their z-scored quality).

    Without methods (every curve skipped) the answers are reference 0, quality 0.
    """
    match = np.zeros(n_q, dtype=np.int64)
    quality = np.zeros(n_q)
    if not flat_ids:
        return match, quality
    for qi in range(n_q):
        fused = flat_fusion(
            [full[m][qi] for m in flat_ids],
            [methods[m].higher_is_better for m in flat_ids],
            faithful=faithful,
        )
        match[qi] = nan_argmax(fused)
        quality[qi] = zscore(fused)[match[qi]]
    return match, quality


def _hierarchy_report(outcome: HierarchyOutcome, tiers: list[dict[str, Any]]) -> dict[str, Any]:
    """The report's ``hierarchy`` entries every evaluation has (route or index)."""
    return {
        "combined_recall_at_1": outcome.recall_at_1,
        "tiers": tiers,
        "pr": pr_curve(outcome.correct, outcome.quality),
    }


def evaluate(
    config: HierarchyConfig,
    data: EvalData,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    skip_curves: Sequence[str] = (),
    progress: bool = False,
    sequence: bool = False,
    foreign: Sequence[Path] = (),
) -> dict[str, Any]:
    """Evaluate every method alone, the hierarchy and flat fusion; returns the JSON report.

    ``skip_curves`` lists method ids whose whole-database score matrix is not computed (their
    recall@N is omitted and flat fusion then uses the remaining methods; the report says so).
    With ``sequence`` the queries are also driven in order as one vehicle along the
    references (one route, file order) through the sequence filter of ``config``
    (:mod:`hmpf.evaluation.sequence`); with ``foreign`` (frames of places the map does not
    hold, in driving order) also drives that leave the map and come back
    (:func:`~hmpf.evaluation.sequence.off_map_report`, report key ``off_map``).
    """
    gt = data.gt
    prep = prepare(build_methods(config), data, cache=cache, workers=workers, progress=progress)
    methods, n_db, n_q = prep.methods, len(data.reference), len(data.query)
    # The hierarchy, per query, scoring on demand (timed independently of the curves).
    scorers = (feature_scorer(methods, prep.query(qi), prep.db) for qi in range(n_q))
    hierarchy = Hierarchy(config, methods)
    results, hierarchy_s = run_queries(hierarchy, scorers, n_db)
    outcome = outcome_of(results, gt, n_db)
    method_report, full, curves_s = _method_curves(prep, gt, skip_curves)
    flat_ids = [m for m in config.method_ids if m in full]
    flat_match, flat_quality = _flat_baseline(full, methods, flat_ids, config.faithful, n_q)
    flat_correct = gt[np.arange(n_q), flat_match]
    tiers = tier_rows(config, outcome)
    report = {
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
            **_hierarchy_report(outcome, tiers),
            "final_tier_recall_at_1": tiers[-1]["top1_recall"],
            "flat_recall_at_1": float(flat_correct.mean()) if flat_ids else None,
            "flat_methods": flat_ids,
            "flat_pr": pr_curve(flat_correct, flat_quality) if flat_ids else None,
            "matches": outcome.matches.tolist(),
            "quality": [None if np.isnan(x) else float(x) for x in outcome.quality],
        },
        "timing_ms": {
            "decode_per_image": median([prep.ref.decode_ms, prep.qry.decode_ms]),
            "extract_per_image": {m: method_report[m]["extract_ms_per_image"] for m in methods},
            "tiers_per_query": [t["ms_per_query"] for t in tiers],
            "fusion_per_query": outcome.fusion_ms,
            "hierarchy_per_query": hierarchy_s * 1e3 / max(1, n_q),
        },
        "wall_s": {
            "fit": prep.fit_s,
            "extraction": prep.extraction_s,
            "hierarchy": hierarchy_s,
            "extraction_plus_hierarchy": prep.extraction_s + hierarchy_s,
            "single_method_curves": curves_s,
        },
        "cache": {"reference_cached": prep.ref.cached, "query_cached": prep.qry.cached},
        "fitted_methods": prep.fitted,
    }
    routes = RouteMap.from_metadata(n_db)

    def built_profile() -> ReferenceProfile:
        prof = ReferenceProfile.build(prep.methods, prep.db, config.tiers[0].methods, routes)
        if config.acceptance is None or not config.acceptance.reads_map_prior:
            return prof
        # the models read the map's prior: what an index of these references would store
        entry = map_prior_or_why(
            config, data.reference, cache=cache, workers=workers, progress=progress
        )
        report["map_prior"] = entry
        return replace(prof, map_prior=entry["map_prior"])

    profile = _once(built_profile)
    params = config.sequence_params()
    tier1 = config.tiers[0].methods
    if params.motion:  # the filter reads each frame's sketch from its result
        sketch_results(results, motion_sketches(prep.methods, tier1, prep.db, prep.queries, routes))
    if sequence:
        report["sequence"] = _sequence(results, gt, routes, config, profile())
    if sequence and foreign:
        # The foreign frames through the methods fitted above, against the same database: only
        # their own features are extracted (the references are not fitted or read again).
        away = extract_images(
            list(foreign), methods, cache=cache, workers=workers, progress=progress, desc="foreign"
        ).features
        scorers = (
            feature_scorer(methods, {m: away[m][qi] for m in methods}, prep.db)
            for qi in range(len(foreign))
        )
        away_results, _ = run_queries(hierarchy, scorers, n_db)
        if params.motion:
            sketch_results(
                away_results, motion_sketches(prep.methods, tier1, prep.db, away, routes)
            )
        report["off_map"] = off_map_report(results, away_results, gt, routes, params, profile())
    report["acceptance"] = acceptance_report(
        results, gt, routes, config, sequence=sequence, profile=profile
    )
    return report


def _once(build: Callable[[], ReferenceProfile]) -> Callable[[], ReferenceProfile]:
    """``build``, called at most once."""
    made: list[ReferenceProfile] = []

    def get() -> ReferenceProfile:
        if not made:
            made.append(build())
        return made[0]

    return get


def _sequence(
    results: Sequence[HierarchyResult],
    gt: np.ndarray,
    routes: RouteMap,
    config: HierarchyConfig,
    profile: ReferenceProfile | None = None,
) -> dict[str, Any]:
    t0 = time.perf_counter()
    rep = sequence_report(results, gt, routes, config.sequence_params(), profile=profile)
    rep["wall_s"] = time.perf_counter() - t0
    return rep


def acceptance_report(
    results: Sequence[HierarchyResult],
    gt: np.ndarray,
    routes: RouteMap,
    config: HierarchyConfig,
    *,
    sequence: bool = False,
    profile: Callable[[], ReferenceProfile] | None = None,
) -> dict[str, Any]:
    """The config's acceptance applied to every answer (:mod:`hmpf.evaluation.acceptance`).

    ``profile`` builds the references' :class:`~hmpf.confidence.ReferenceProfile`; called
    only when a model needs it.

    ``single`` (and with ``sequence`` ``sequence``: the queries driven once, in order):
    ``rule`` (``p_correct``, ``quality`` or ``lock``: the one policy the service runs,
    :mod:`hmpf.acceptance`), per answer ``p_correct`` (None without a model),
    ``accepted_answers`` and ``off_map``, and ``accepted`` (share), ``precision`` and, for
    the model, ``ece``.
    """
    params = config.sequence_params()
    policy = Policy.of(config.acceptance, lock_mass=params.lock_mass)
    # The sequence filter's off-map state reads the profile too.
    prof = profile() if profile and (policy.needs_profile or sequence) else None
    prof = policy.with_map_prior(prof)
    out = {"single": apply_acceptance(policy, single_answers(results, gt, routes, prof))}
    if sequence:
        seq = sequence_answers(results, gt, routes, params, profile=prof)
        out["sequence"] = apply_acceptance(policy, seq, sequence=True)
    return out


def evaluate_index(
    reader: IndexReader,
    queries: Sequence[Path],
    gt: np.ndarray,
    ground_truth: str,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    progress: bool = False,
    sequence: bool = False,
) -> dict[str, Any]:
    """Queries against a built index, through exactly what the service runs per query.

    With ``sequence`` the queries are also driven in order as one vehicle along the index's
    routes (:meth:`~hmpf.index.reader.IndexReader.route_map`).

    Reports the hierarchy's recall, its tier table, the PR curve over the quality score and
    timings; single-method curves and flat fusion need whole-database score matrices and are
    left to :func:`evaluate`. ``gt`` is (n_query, n_ref) over the index's places
    (:attr:`~hmpf.index.reader.IndexReader.place_names`); a matrix over every row of a
    version with experiences is cut to its places' columns (an experience is a picture of
    its place, not another place).
    """
    if gt.shape[1] == reader.n_rows != reader.n:
        gt = gt[:, : reader.n]
    t0 = time.perf_counter()
    qry = extract_images(
        queries, reader.methods, cache=cache, workers=workers, progress=progress, desc="queries"
    )
    extraction_s = time.perf_counter() - t0
    scorers = (
        reader.scorer({m: qry.features[m][qi] for m in reader.methods})
        for qi in range(len(queries))
    )
    results, hierarchy_s = run_queries(reader.hierarchy(), scorers, reader.n)
    outcome = outcome_of(results, gt, reader.n)
    report = {
        "index": {
            "path": str(reader.root),
            "version": reader.version,
            "n_reference": reader.n,
            "n_experiences": reader.n_rows - reader.n,
        },
        "config": {"name": reader.config.name, "sha256": reader.config.digest()},
        "protocol": {
            "query": str(Path(queries[0]).parent),
            "n_query": len(queries),
            "ground_truth": ground_truth,
        },
        "hierarchy": {
            **_hierarchy_report(outcome, tier_rows(reader.config, outcome)),
            "matches": [reader.refs.names[m] if m >= 0 else None for m in outcome.matches],
        },
        "wall_s": {"extraction": extraction_s, "hierarchy": hierarchy_s},
        "timing_ms": {"hierarchy_per_query": hierarchy_s * 1e3 / max(1, len(queries))},
    }
    motion = reader.motion_sketch()
    if motion is not None:  # the filter reads each frame's sketch from its result
        mid, sketch = motion
        sketch_results(results, [sketch(f) for f in qry.features[mid]])
    if sequence:
        report["sequence"] = _sequence(
            results, gt, reader.route_map(), reader.config, reader.reference_profile()
        )
    report["acceptance"] = acceptance_report(
        results,
        gt,
        reader.route_map(),
        reader.config,
        sequence=sequence,
        profile=reader.reference_profile,
    )
    return report


# -- reports as text ---------------------------------------------------------------------------


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
    lines.extend(format_tier_table(h["tiers"]))
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
    lines.extend(_sequence_lines(report))
    lines.extend(_acceptance_lines(report))
    w = report["wall_s"]
    tm = report["timing_ms"]
    lines.append(
        f"time: extraction {w['extraction']:.1f} s, hierarchy {w['hierarchy']:.1f} s "
        f"({tm['hierarchy_per_query']:.1f} ms/query), single-method curves "
        f"{w['single_method_curves']:.1f} s"
    )
    return "\n".join(lines)


def format_index_report(report: dict[str, Any]) -> str:
    """Human-readable summary of :func:`evaluate_index`'s report."""
    i, p, h = report["index"], report["protocol"], report["hierarchy"]
    lines = [
        f"{report['config']['name']}: index {i['path']} ({i['version']}, {i['n_reference']} refs)"
        f" <- {p['query']} [{p['n_query']} queries, ground truth {p['ground_truth']}]",
        *format_tier_table(h["tiers"]),
    ]
    pr = h["pr"]
    lines += [
        f"Combined recall@1   {h['combined_recall_at_1']:.3f}",
        f"PR (quality): AUC {pr['auc']:.3f}  max F1 {pr['max_f1']:.3f}  "
        f"recall@100%P {pr['recall_at_100_precision']:.3f}",
        *_sequence_lines(report),
        *_acceptance_lines(report),
        f"time: query extraction {report['wall_s']['extraction']:.1f} s, hierarchy "
        f"{report['wall_s']['hierarchy']:.1f} s "
        f"({report['timing_ms']['hierarchy_per_query']:.1f} ms/query)",
    ]
    return "\n".join(lines)


def _acceptance_lines(report: dict[str, Any]) -> list[str]:
    """One line per mode: the rule that decided and its figures."""
    lines = []
    for mode, a in report.get("acceptance", {}).items():
        prec = "n/a" if a["precision"] is None else f"{a['precision']:.3f}"
        ece = f", ECE {a['ece']:.3f}" if a.get("ece") is not None else ""
        what = {"p_correct": "p_correct", "quality": "Combined z", "lock": "posterior mass"}
        off = a.get("off_map") or []
        away = f", said off the map {sum(off)}/{len(off)}" if mode == "sequence" and off else ""
        lines.append(
            f"acceptance ({mode}, rule {a['rule']}: {what[a['rule']]} >= "
            f"{a['threshold']:.4g}): accepted {a['accepted']:.3f}, precision {prec}{ece}{away}"
        )
    return lines


def _sequence_lines(report: dict[str, Any]) -> list[str]:
    if "sequence" not in report:
        return []
    lines = ["", "sequence mode (queries driven in order as one vehicle):"] + [
        "  " + line for line in format_sequence_report(report["sequence"])
    ]
    if "off_map" in report:
        lines += ["", "leaving the map and coming back (--foreign frames):"] + [
            "  " + line for line in format_off_map_report(report["off_map"])
        ]
    return lines
