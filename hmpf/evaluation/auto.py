"""The automatic choice of a hierarchy from the references alone (``--config auto``).

:func:`choose_config` is what ``hmpf-calibrate --auto`` runs and what an index build calls:

0. **Thumbnails** (:data:`SMALL_SIDE`): references under 128 px on their shorter side take
   the ``thumbnails`` preset as it ships, and none of the steps below runs.
1. **Plan** (:func:`hmpf.evaluation.pseudo.plan`): at most ``max_references`` references
   (stretches spread along the routes) become the map; along each route, stretches take the
   roles fit / search / fit / check; at most ``max_queries`` pseudo-queries are made from the
   search and check stretches, each a reference changed as a camera's view changes between
   drives.
2. **Score bank** (:func:`pseudo_bank`): every pool method is fitted on the *fit* references
   only (so no pseudo-query comes from an image anything was fitted on), extracts every map
   reference and every pseudo-query (through the feature cache), and scores every
   pseudo-query against the whole map. Each pseudo-query's own reference is then masked
   (:func:`mask_sources`): its score is set to that row's worst, which leaves every other
   reference's normalised score as it would be without it and ranks it last, and it is
   never right in the ground truth. The bank is a :class:`~hmpf.evaluation.study.ScoreBank`
   like ``hmpf-calibrate``'s, so every hierarchy runs through the real hierarchy code.
3. **Search** on the *search* pseudo-queries: the same search ``hmpf-calibrate`` runs
   (:func:`hmpf.evaluation.calibrate.search`: the pool, 1-3 tiers, candidate counts and
   weights, the per-query time budget on a cost model charged for the whole map), plus the
   bundled presets of :data:`SHELF` whose methods the pool holds with the same settings, as
   they ship.
4. **Check** on the *check* pseudo-queries, held out from the search: the best candidate of
   the search replaces the incumbent (:data:`INCUMBENT`, the default preset) only when it wins
   more held-out pseudo-queries than it loses with a paired sign test below ``alpha``
   (:func:`hmpf.evaluation.metrics.paired_test`). A hierarchy is left for another only on
   evidence the search did not choose it on: a rule meant to carry to a camera nobody
   measured, rather than one tuned to the routes we have.
5. **Acceptance**: the chosen hierarchy's z threshold and confidence models are fitted on all
   pseudo-query answers, by the step ``hmpf-calibrate --fit-only`` runs
   (:func:`hmpf.evaluation.calibrate.fit_config_acceptance`). A bundled preset that ships
   confidence models and is kept as it ships keeps those instead (they were fitted on real
   queries and measured better; the pseudo-query fit's figures stay in the record).

The result is a config (a preset chosen as it ships keeps its name and digest) and a
JSON-able record of why: every candidate's pseudo-query recall on the search and the check
part, the test, the seed, the sample sizes and the time each step took.

Deterministic for a seed: the plan, the changes and the search's draws follow it, and the
cost model that enforces the budget and breaks ties is :data:`NOMINAL_COSTS` (fixed figures,
so the choice does not depend on the machine's load) unless another is given.
"""

from __future__ import annotations

import contextlib
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from hmpf.config import (
    HierarchyConfig,
    build_methods,
    load_config,
    parse_config,
    shipped_acceptance,
)
from hmpf.errors import ConfigError, DatasetError
from hmpf.evaluation.calibrate import (
    SearchSpace,
    Trial,
    describe,
    fit_config_acceptance,
    search,
)
from hmpf.evaluation.data import EvalData
from hmpf.evaluation.metrics import HierarchyOutcome, paired_test
from hmpf.evaluation.pseudo import PseudoPlan, RoutePositions, plan, route_positions
from hmpf.evaluation.study import CostModel, ScoreBank, check_compatible, measure_costs
from hmpf.features import FeatureCache, extract_images, fit_methods
from hmpf.imageio import load_image
from hmpf.runtime import machine_description

__all__ = [
    "AUTO_POOL",
    "INCUMBENT",
    "NOMINAL_COSTS",
    "SHELF",
    "SMALL_PRESET",
    "SMALL_SIDE",
    "AutoResult",
    "Candidate",
    "Choice",
    "auto",
    "auto_pool",
    "choose",
    "choose_config",
    "mask_sources",
    "nominal_costs",
    "pseudo_bank",
    "reference_size",
]

#: The methods the automatic choice may use: the default preset's (multi-scale GeM, NetVLAD
#: on Lite1, OLO, Gist) and the ``thumbnails`` preset's (HOG, whitened HOG, SAD and Gist),
#: with SAD: so both presets, the two ends of the camera range (full-resolution street
#: views, low-resolution thumbnails), are hierarchies of the pool, and the search can mix
#: them. KAZE and HybridNet are left out (KAZE's pair matching dominates a score bank's
#: time; neither is in a preset the choice starts from). ``tier_score: mean`` as
#: ``calibration-pool``.
AUTO_POOL: dict[str, Any] = {
    "name": "auto-pool",
    "description": "Every method the automatic choice may use, fused flat over the database.",
    "tier_score": "mean",
    "methods": {
        "gem": {"scales": [1.0, 0.5]},
        "netvlad": {"clusters": 32, "backbone": "efficientnet_lite1"},
        "olo": {"regions": 100},
        "hog_w": {"type": "hog", "whiten": 4096, "whiten_power": 0.25, "whiten_shrink": 0.1},
        "sad_w": {"type": "sad", "whiten": 4096, "whiten_power": 0.5, "whiten_shrink": 1.0},
        "gist_w": {"type": "gist", "whiten": 4096, "whiten_power": 0.5, "whiten_shrink": 1.0},
    },
    "tiers": [
        {
            "methods": ["gem", "netvlad", "olo", "gist", "hog", "sad", "hog_w", "sad_w", "gist_w"],
            "k": 1,
        }
    ],
}

#: Bundled presets tried as they ship, besides the search's hierarchies, where the pool holds
#: their methods with the same settings.
SHELF = ("default", "thumbnails", "single-tier")
#: The hierarchy kept unless another wins on held-out pseudo-queries: what a user who picks
#: nothing gets.
INCUMBENT = "default"
#: References whose shorter side is below this many pixels (the median over a sample) are
#: thumbnails: the choice is :data:`SMALL_PRESET`, without a search. Pseudo-queries do not
#: predict real queries there: on Nordland's 64 x 32 thumbnails the search's best beat the
#: default on held-out pseudo-queries and lost far to the ``thumbnails`` preset on real
#: winter queries (``bench.auto_config`` measures the search beside the rule:
#: ``docs/results/auto_config.md``). A pseudo-query changes a reference's exposure, blur or
#: crop, not its season, and at that size what the CNN methods match best is the reference
#: itself. 128 is a round figure below every camera frame the presets were chosen on and far
#: above the thumbnails; only one route of each kind is here, so it was set by that
#: reasoning, not tuned.
SMALL_SIDE = 128
#: The preset for thumbnails (HOG, whitened HOG, SAD and Gist: methods made for a few
#: thousand pixels).
SMALL_PRESET = "thumbnails"
#: References whose size :func:`reference_size` reads (spread evenly along the list).
SIZE_SAMPLE = 16

#: Per-query cost figures of :data:`AUTO_POOL`'s methods (ms, one compute thread), used for
#: the time budget and the search's tie-break so that the choice is the same on any machine
#: and under any load. Measured once by :func:`~hmpf.evaluation.study.measure_costs` (12
#: night_right queries, 100 day_right references: 960 x 540 and 640 x 360 images) on the
#: development machine (AMD EPYC, 2 cores shared with other jobs, load average 2.6, one BLAS
#: thread), then every figure scaled by 0.54 so that the default preset's query extraction
#: comes to its quiet-machine measurement (66.5 ms, docs/scale.md); ``n_db`` is replaced by
#: the map's size.
NOMINAL_COSTS: dict[str, Any] = {
    "units_ms": {
        "forward:0": 10.16,
        "head:gem": 0.265,
        "forward:1": 27.93,
        "head:netvlad": 0.212,
        "forward:2": 21.92,
        "head:olo": 2.346,
        "extract:gist": 3.667,
        "extract:hog": 3.107,
        "extract:sad": 0.766,
        "extract:hog_w": 3.159,
        "extract:sad_w": 0.806,
        "extract:gist_w": 4.232,
    },
    "method_units": {
        "gem": ["forward:0", "head:gem"],
        "netvlad": ["forward:1", "head:netvlad"],
        "olo": ["forward:2", "head:olo"],
        "gist": ["extract:gist"],
        "hog": ["extract:hog"],
        "sad": ["extract:sad"],
        "hog_w": ["extract:hog_w"],
        "sad_w": ["extract:sad_w"],
        "gist_w": ["extract:gist_w"],
    },
    "match_ms": {
        "gem": {"a": 0.01848, "b_per_ref": 4.9e-06},
        "netvlad": {"a": 0.0539, "b_per_ref": 0.0},
        "olo": {"a": 0.0, "b_per_ref": 0.0457587},
        "gist": {"a": 0.00567, "b_per_ref": 0.0002824},
        "hog": {"a": 0.02056, "b_per_ref": 6.79e-05},
        "sad": {"a": 0.00652, "b_per_ref": 5.34e-05},
        "hog_w": {"a": 0.00588, "b_per_ref": 2.98e-05},
        "sad_w": {"a": 0.00601, "b_per_ref": 2.96e-05},
        "gist_w": {"a": 0.00899, "b_per_ref": 2.96e-05},
    },
    "fusion_ms_per_tier": 0.0591,
    "n_db": 100,
    "threads": 1,
}


def auto_pool() -> HierarchyConfig:
    """:data:`AUTO_POOL` as a config."""
    return parse_config(AUTO_POOL, "auto-pool")


def nominal_costs(pool: HierarchyConfig, n_db: int) -> CostModel | None:
    """:data:`NOMINAL_COSTS` charged for ``n_db`` references, or None when it lacks one of
    the pool's methods (with other settings than :data:`AUTO_POOL`'s, or another method)."""
    nominal = parse_config(AUTO_POOL, "auto-pool")
    model = CostModel.from_dict(NOMINAL_COSTS)
    for mid in pool.method_ids:
        if mid not in model.method_units or mid not in nominal.method_ids:
            return None
        if pool.method_spec(mid) != nominal.method_spec(mid):
            return None
    return CostModel(
        model.units, model.method_units, model.match, model.fusion_ms, n_db, model.threads
    )


# -- the score bank of pseudo-queries ----------------------------------------------------------


def mask_sources(scores: np.ndarray, sources: np.ndarray, higher_is_better: bool) -> np.ndarray:
    """``scores`` (pseudo-queries x map) with each row's source column set to the row's worst
    score among the other references.

    The worst is a value the row already has, so min-max normalisation over the map (or over
    any candidate list holding the source) gives every other reference the score it would
    have without the source, and the source the worst one (0): it ranks last, so it is no
    candidate of a tier that passes on fewer than all references, and never the answer of a
    tier that has better ones.
    """
    out = np.array(scores, dtype=np.float64, copy=True)
    rows = np.arange(out.shape[0])
    src = np.asarray(sources, np.int64)
    others = out.copy()
    others[rows, src] = np.nan
    with np.errstate(all="ignore"):
        worst = np.nanmin(others, axis=1) if higher_is_better else np.nanmax(others, axis=1)
    out[rows, src] = worst
    return out


def pseudo_bank(
    pool: HierarchyConfig,
    reference_paths: Sequence[str | Path],
    plan_: PseudoPlan,
    folder: str | Path,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    progress: bool = False,
) -> tuple[ScoreBank, dict[str, float]]:
    """The pool's scores of every pseudo-query against the plan's map, sources masked.

    The pool's methods are fitted on the plan's fit references; the pseudo-queries are
    written to ``folder`` as PNG files (the features come through the cache, keyed by their
    bytes, so a rerun with the same seed extracts nothing). Returns the bank (its ``data``
    names the map's and the pseudo-queries' files) and the seconds each step took.
    """
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    methods = build_methods(pool)
    paths = [Path(p) for p in reference_paths]
    fit_methods(methods, [paths[int(i)] for i in plan_.fit], cache=cache)
    times["fit_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    db_paths = [paths[int(i)] for i in plan_.db]
    query_paths = _write_pseudo_queries(db_paths, plan_, Path(folder))
    times["make_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref = extract_images(
        db_paths, methods, cache=cache, workers=workers, progress=progress, desc="references"
    )
    qry = extract_images(
        query_paths, methods, cache=cache, workers=workers, progress=progress, desc="pseudo"
    )
    times["extract_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scores: dict[str, np.ndarray] = {}
    feats: dict[str, tuple[Any, list[Any]]] = {}
    with _one_blas_thread():
        for mid, m in methods.items():
            db = m.stack_references(ref.features[mid])
            qs = list(qry.features[mid])
            # Per query with subset None: exactly what the hierarchy's scorer computes.
            raw = np.stack([np.asarray(m.scores(q, db), np.float64) for q in qs])
            scores[mid] = mask_sources(raw, plan_.sources, m.higher_is_better)
            feats[mid] = (db, qs)
    times["score_s"] = time.perf_counter() - t0
    data = EvalData(db_paths, query_paths, plan_.gt, f"pseudo-queries: {plan_.truth}")
    return ScoreBank(methods, scores, plan_.gt.copy(), data, feats), times


def map_prior(
    config: HierarchyConfig,
    reference_paths: Sequence[str | Path],
    *,
    metadata: Mapping[str, Any] | None = None,
    cache: FeatureCache | None = None,
    seed: int = 0,
    workers: int | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """How well ``config`` tells the map's own places apart: its recall@1 on pseudo-queries
    made from the references (:func:`~hmpf.evaluation.pseudo.plan`, :func:`pseudo_bank`),
    and ``map_prior``, that recall's log-odds (the recall kept within half a query of 0 and
    1, so the log-odds stay finite). No query and no ground truth are needed, so an index
    can store it when a version is written; the acceptance models read it as the
    ``map_prior`` offset (``docs/experiments/acceptance/README.md``).

    Raises:
        DatasetError: too few references along a route to make pseudo-queries from.
    """
    t0 = time.perf_counter()
    paths = [Path(p) for p in reference_paths]
    plan_ = plan(route_positions(len(paths), metadata), seed=seed)
    with tempfile.TemporaryDirectory(prefix="hmpf-map-prior-") as tmp:
        bank, _ = pseudo_bank(
            config, paths, plan_, Path(tmp), cache=cache, workers=workers, progress=progress
        )
        right = [bool(bank.gt[i, r.match]) for i, r in enumerate(bank.results(config))]
    n = len(right)
    recall = float(np.mean(right))
    kept = min(max(recall, 0.5 / n), 1.0 - 0.5 / n)
    return {
        "references": len(paths),
        "pseudo_queries": n,
        "seed": seed,
        "recall_at_1": recall,
        "map_prior": float(np.log(kept / (1.0 - kept))),
        "seconds": round(time.perf_counter() - t0, 3),
    }


def map_prior_or_why(
    config: HierarchyConfig, reference_paths: Sequence[str | Path], **kwargs: Any
) -> dict[str, Any]:
    """:func:`map_prior`, or, with too few references to make pseudo-queries from,
    ``{"map_prior": None, "why_none": <the reason>}`` (``kwargs``: :func:`map_prior`'s)."""
    try:
        return map_prior(config, reference_paths, **kwargs)
    except DatasetError as exc:
        return {"map_prior": None, "why_none": str(exc)}


def _one_blas_thread() -> contextlib.AbstractContextManager[Any]:
    """One BLAS thread while scoring: one query's products are small, and a multi-threaded
    BLAS on a busy machine stalls on them (OLO's batched products against 100 references:
    1.7 s instead of 6 ms on two shared cores)."""
    try:
        # threadpoolctl is optional (the service's extra): without it the pools keep their sizes.
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - installed with the service extra
        return contextlib.nullcontext()
    return threadpool_limits(1)


def _write_pseudo_queries(db_paths: Sequence[Path], plan_: PseudoPlan, folder: Path) -> list[Path]:
    """Each pseudo-query as ``folder/pseudo_<q>.png``, made from its source's image."""
    folder.mkdir(parents=True, exist_ok=True)
    out: list[Path] = []
    decoded: dict[int, np.ndarray] = {}
    for q, (src, t) in enumerate(zip(plan_.sources, plan_.transforms, strict=True)):
        col = int(src)
        if col not in decoded:
            decoded = {col: load_image(db_paths[col])}  # sources come in runs of copies
        img = t.apply(decoded[col])
        path = folder / f"pseudo_{q:05d}.png"
        if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {path}")
        out.append(path)
    return out


# -- the choice --------------------------------------------------------------------------------


@dataclass
class Candidate:
    """A hierarchy the choice considered: a search trial or a bundled preset as it ships.

    Attributes:
        name: the preset's name, or ``search`` for a trial of the search.
        config: the hierarchy.
        search: its outcome on the search pseudo-queries.
        model_ms: its modelled time per query for the whole map.
        check: its outcome on the check pseudo-queries, once measured.
    """

    name: str
    config: HierarchyConfig
    search: HierarchyOutcome
    model_ms: float
    check: HierarchyOutcome | None = None

    @property
    def label(self) -> str:
        c = self.config
        text = describe([t.methods for t in c.tiers], [t.k for t in c.tiers], c.tier_weights)
        return text if self.name == "search" else f"{self.name}: {text}"

    def sort_key(self) -> tuple[Any, ...]:
        n_methods = len(self.config.method_ids)
        return (
            -self.search.recall_at_1,
            self.model_ms,
            n_methods,
            len(self.config.tiers),
            self.label,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "hierarchy": self.label,
            "digest": self.config.digest(),
            "search_recall_at_1": self.search.recall_at_1,
            "check_recall_at_1": None if self.check is None else self.check.recall_at_1,
            "model_ms": self.model_ms,
        }


def _shelf(
    pool: HierarchyConfig,
    names: Sequence[str],
    bank: ScoreBank,
    costs: CostModel,
    budget_ms: float | None,
) -> tuple[list[Candidate], dict[str, str]]:
    """The presets of ``names`` the pool can run, on ``bank``; and why the others are not."""
    out: list[Candidate] = []
    skipped: dict[str, str] = {}
    for name in names:
        config = load_config(name)
        try:
            check_compatible(config, pool)
        except ConfigError as exc:
            skipped[name] = str(exc)
            continue
        outcome = bank.run(config)
        ms = costs.query_ms(config, outcome.mean_inputs)
        if budget_ms is not None and ms > budget_ms:
            skipped[name] = f"over the budget: {ms:.1f} ms per query modelled"
            continue
        out.append(Candidate(name, config, outcome, ms))
    return out, skipped


@dataclass
class Choice:
    """What :func:`choose` decided.

    Attributes:
        chosen: the chosen candidate.
        record: the JSON-able record (candidates, the held-out test, the decision, times).
        candidates: the candidates, best on the search pseudo-queries first.
        ranked: every hierarchy the search tried within the budget, best first.
    """

    chosen: Candidate
    record: dict[str, Any]
    candidates: list[Candidate]
    ranked: list[Trial]


def _trial_candidate(trial: Trial, pool: HierarchyConfig, name: str) -> Candidate:
    assert trial.outcome is not None
    return Candidate("search", trial.config(pool, name=name), trial.outcome, trial.model_ms)


def choose(
    bank: ScoreBank,
    plan_: PseudoPlan,
    pool: HierarchyConfig,
    costs: CostModel,
    space: SearchSpace,
    *,
    budget_ms: float | None = 150.0,
    seed: int = 0,
    alpha: float = 0.05,
    shelf: Sequence[str] = SHELF,
    incumbent: str | None = INCUMBENT,
    name: str = "auto",
    top: int = 20,
    progress: Callable[[int, int], Any] | None = None,
) -> Choice:
    """Steps 3 and 4 of the module docstring on a pseudo-query bank (see :class:`Choice`)."""
    t0 = time.perf_counter()
    search_bank = bank.rows(plan_.queries("search"))
    check_bank = bank.rows(plan_.queries("check"))
    ranked = search(
        search_bank, pool, costs, space, budget_ms=budget_ms, seed=seed, progress=progress
    )
    presets, skipped = _shelf(pool, shelf, search_bank, costs, budget_ms)
    best_of: dict[tuple[tuple[str, ...], ...], Trial] = {}
    for t in ranked:  # the best trial of each structure, so the candidates differ
        if t.tiers not in best_of:
            best_of[t.tiers] = t
        if len(best_of) >= top:
            break
    found = [_trial_candidate(t, pool, name) for t in best_of.values()]
    candidates = sorted([*presets, *found], key=Candidate.sort_key)
    if not candidates:
        raise ConfigError(
            f"no hierarchy of the pool {pool.name!r} fits the budget of {budget_ms} ms per query"
        )
    search_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for c in candidates:
        c.check = check_bank.run(c.config)
    challenger = candidates[0]
    held = next((c for c in presets if c.name == incumbent), None)
    test: dict[str, Any] | None = None
    if held is None:
        chosen = challenger
        why = (
            f"the incumbent {incumbent!r} is not a candidate "
            f"({skipped.get(str(incumbent), 'not asked for')}): the search's best is taken"
        )
    elif challenger is held:
        chosen = held
        why = f"the incumbent {incumbent!r} is the best on the search pseudo-queries"
    else:
        assert challenger.check is not None and held.check is not None
        test = paired_test(challenger.check.correct, held.check.correct)
        if test["wins"] > test["losses"] and test["p"] < alpha:
            chosen = challenger
            why = (
                f"the search's best wins {test['wins']} and loses {test['losses']} held-out "
                f"pseudo-queries against {incumbent!r} (sign test p = {test['p']:.2g} < {alpha:g})"
            )
        else:
            chosen = held
            why = (
                f"the search's best wins {test['wins']} and loses {test['losses']} held-out "
                f"pseudo-queries against {incumbent!r} (sign test p = {test['p']:.2g}, not "
                f"below {alpha:g}): {incumbent!r} is kept"
            )
    record: dict[str, Any] = {
        "evaluated": len(ranked),
        "candidates": [c.to_dict() for c in candidates],
        "shelf_skipped": skipped,
        "incumbent": None if held is None else held.to_dict(),
        "challenger": challenger.to_dict(),
        "alpha": alpha,
        "check_test": test,
        "chosen": {**chosen.to_dict(), "why": why},
        "search_s": search_s,
        "check_s": time.perf_counter() - t0,
    }
    return Choice(chosen, record, candidates, ranked)


def _space_dict(space: SearchSpace) -> dict[str, Any]:
    return {
        "methods": list(space.methods),
        "max_tiers": space.max_tiers,
        "max_per_tier": space.max_per_tier,
        "k1": list(space.k1),
        "k2": list(space.k2),
        "samples": space.samples,
        "refine": space.refine,
    }


@dataclass
class AutoResult:
    """Everything :func:`auto` computed (the benches read the bank and the ranked trials).

    Attributes:
        config: the chosen config with its fitted acceptance.
        reasons: the JSON-able record of the choice.
        bank: the pseudo-query score bank (its pseudo-query files are gone after the call
            unless ``workdir`` was given); None for thumbnails (:data:`SMALL_SIDE`: no
            pseudo-query is made).
        plan: the plan of the references and pseudo-queries (None for thumbnails).
        candidates: the candidates, best on the search pseudo-queries first (none for
            thumbnails).
        ranked: every hierarchy the search tried within the budget, best first.
        costs: the cost model used (charged for the whole map).
    """

    config: HierarchyConfig
    reasons: dict[str, Any]
    bank: ScoreBank | None
    plan: PseudoPlan | None
    candidates: list[Candidate]
    ranked: list[Trial]
    costs: CostModel | None


def choose_config(
    reference_paths: Sequence[str | Path],
    metadata: Mapping[str, Any] | None = None,
    *,
    seed: int = 0,
    cache: FeatureCache | None = None,
    **options: Any,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """Choose a hierarchy and fit its acceptance from the references alone: what an index
    build with ``--config auto`` calls (:func:`auto` has the options).

    Returns:
        The config (a bundled preset chosen as it ships keeps its name and digest; a
        hierarchy the search found is named ``auto``) with its acceptance (fitted on the
        pseudo-queries; a preset that ships models keeps them, :func:`_kept_acceptance`),
        and the JSON-able record of why (the candidates and their pseudo-query recall, the
        held-out test, the seed, the sample sizes, the time taken, the config).
    """
    result = auto(reference_paths, metadata, seed=seed, cache=cache, **options)
    return result.config, result.reasons


def auto(
    reference_paths: Sequence[str | Path],
    metadata: Mapping[str, Any] | None = None,
    *,
    seed: int = 0,
    cache: FeatureCache | None = None,
    pool: HierarchyConfig | None = None,
    space: SearchSpace | None = None,
    budget_ms: float | None = 150.0,
    costs: CostModel | None = None,
    alpha: float = 0.05,
    shelf: Sequence[str] = SHELF,
    incumbent: str | None = INCUMBENT,
    max_references: int = 1000,
    max_queries: int = 400,
    tolerance: int = 2,
    radius_m: float | None = 25.0,
    target_precision: float = 0.99,
    model: bool = True,
    outside: bool = True,
    name: str = "auto",
    workers: int | None = None,
    progress: bool = False,
    search_progress: Callable[[int, int], Any] | None = None,
    workdir: str | Path | None = None,
    small_side: int | None = SMALL_SIDE,
) -> AutoResult:
    """Choose a hierarchy and fit its acceptance from the references alone.

    References smaller than ``small_side`` pixels on their shorter side (the median of
    :func:`reference_size`'s sample) are thumbnails: the :data:`SMALL_PRESET` preset is
    taken as it ships, without pseudo-queries or a search (:data:`SMALL_SIDE` says why;
    ``None``: always search).

    Args:
        reference_paths: the map's images, in file order.
        metadata: columns aligned with ``reference_paths`` as the indexer reads a metadata
            CSV (``sequence``, ``timestamp``, ``lat``, ``lon``; others ignored): route order
            and, with GPS, what is right (within ``radius_m`` metres).
        seed: the plan's, the changes' and the search's seed.
        cache: the feature cache (pass the build's: the chosen methods' reference features
            are then already there when they have the pool's settings and fit).
        pool: the methods the search may use (default :data:`AUTO_POOL`).
        space: the search space (default: ``hmpf-calibrate``'s over the pool's methods).
        budget_ms, costs: the per-query time budget and the cost model it is enforced on
            (default: :data:`NOMINAL_COSTS` for the pool's methods, else measured on the
            pseudo-queries), charged for every reference of the map.
        alpha: the held-out test's level for leaving ``incumbent``.
        max_references, max_queries: the bound on the images looked at (see
            :func:`hmpf.evaluation.pseudo.plan`).
        tolerance, radius_m: what is right for a pseudo-query (frames along the route; GPS).
        target_precision, model, outside: the acceptance fit, as ``hmpf-calibrate``.
        workdir: where the pseudo-query images are written (default: a temporary folder,
            removed afterwards).
        small_side: the thumbnail rule's bound in pixels (None: no rule).

    Returns:
        The config (a preset chosen as it ships keeps its name and digest; else ``name``)
        with its acceptance (:func:`_kept_acceptance`), the JSON-able record of the
        choice, and what the benches read (:class:`AutoResult`).
    """
    t_start = time.perf_counter()
    pool = pool if pool is not None else auto_pool()
    space = space if space is not None else SearchSpace(tuple(pool.method_ids))
    n = len(reference_paths)
    where: RoutePositions = route_positions(n, metadata)  # checks the metadata either way
    if small_side is not None:
        size = reference_size(reference_paths)
        if min(size) < small_side:
            return _thumbnails_choice(size, small_side, n, seed, pool, costs, budget_ms, t_start)
    plan_ = plan(
        where,
        seed=seed,
        max_references=max_references,
        max_queries=max_queries,
        tolerance=tolerance,
        radius_m=radius_m,
    )
    with tempfile.TemporaryDirectory(prefix="hmpf-auto-") as tmp:
        folder = Path(workdir) if workdir is not None else Path(tmp)
        bank, times = pseudo_bank(
            pool, reference_paths, plan_, folder, cache=cache, workers=workers, progress=progress
        )
        costs_source = "given"
        if costs is None:
            costs = nominal_costs(pool, n)
            costs_source = "nominal"
        if costs is None:
            t0 = time.perf_counter()
            costs = measure_costs(bank, n_db=n)
            times["costs_s"] = time.perf_counter() - t0
            costs_source = "measured"
        else:
            costs = CostModel(
                costs.units, costs.method_units, costs.match, costs.fusion_ms, n, costs.threads
            )
        choice = choose(
            bank,
            plan_,
            pool,
            costs,
            space,
            budget_ms=budget_ms,
            seed=seed,
            alpha=alpha,
            shelf=shelf,
            incumbent=incumbent,
            name=name,
            progress=search_progress,
        )
        record = choice.record
        t0 = time.perf_counter()
        fit = fit_config_acceptance(
            choice.chosen.config,
            bank,
            target_precision=target_precision,
            seed=seed,
            model=model,
            outside=outside,
        )
        times["acceptance_s"] = time.perf_counter() - t0
    config, source = _kept_acceptance(choice.chosen.config, fit.config)
    times["search_s"] = record.pop("search_s")
    times["check_s"] = record.pop("check_s")
    times["total_s"] = time.perf_counter() - t_start
    kinds = _transform_kinds(plan_)
    reasons: dict[str, Any] = {
        "mode": "auto",
        "machine": machine_description(),
        "seed": seed,
        "pool": pool.name,
        "space": _space_dict(space),
        "budget_ms": budget_ms,
        "costs_source": costs_source,
        "costs": costs.to_dict(),
        "sample": {
            **plan_.summary(),
            "max_references": max_references,
            "max_queries": max_queries,
            "tolerance": tolerance,
            "radius_m": radius_m,
            "metadata": sorted(k for k, v in (metadata or {}).items() if v is not None),
        },
        "changes": kinds,
        **record,
        "acceptance_source": source,
        "acceptance": _acceptance_figures(fit.acceptance, fit.confidence),
        "digest": config.digest(),
        "time_s": times,
        "config": config.model_dump(mode="json"),
    }
    return AutoResult(config, reasons, bank, plan_, choice.candidates, choice.ranked, costs)


def reference_size(reference_paths: Sequence[str | Path]) -> tuple[int, int]:
    """The references' (width, height): the median of each over :data:`SIZE_SAMPLE`
    references spread evenly along the list (every reference of a shorter list)."""
    n = len(reference_paths)
    if n == 0:
        raise ConfigError("no references to choose a hierarchy from")
    picks = np.unique(np.linspace(0, n - 1, min(SIZE_SAMPLE, n)).round().astype(int))
    shapes = np.array([load_image(reference_paths[int(i)]).shape[:2] for i in picks])
    height, width = np.median(shapes, axis=0)
    return int(width), int(height)


def _thumbnails_choice(
    size: tuple[int, int],
    small_side: int,
    n: int,
    seed: int,
    pool: HierarchyConfig,
    costs: CostModel | None,
    budget_ms: float | None,
    t_start: float,
) -> AutoResult:
    """The choice for thumbnails (:data:`SMALL_SIDE`): :data:`SMALL_PRESET` as it ships."""
    config = load_config(SMALL_PRESET)
    own = shipped_acceptance().get(config.digest())
    if own is not None:
        config = config.model_copy(update={"acceptance": own})
    costs = nominal_costs(pool, n) if costs is None else costs
    why = (
        f"the references are {size[0]} x {size[1]} px, below {small_side} px on the shorter "
        f"side: thumbnails, for which pseudo-queries do not predict real queries; the "
        f"{SMALL_PRESET!r} preset is taken as it ships, without a search"
    )
    reasons: dict[str, Any] = {
        "mode": "auto",
        "machine": machine_description(),
        "seed": seed,
        "pool": pool.name,
        "budget_ms": budget_ms,
        "rule": {"image_size": list(size), "small_side": small_side, "preset": SMALL_PRESET},
        "sample": {"references": n, "sized": min(SIZE_SAMPLE, n)},
        "evaluated": 0,
        "candidates": [],
        "chosen": {"hierarchy": SMALL_PRESET, "source": "rule", "why": why},
        "acceptance_source": "shipped" if own is not None else "the preset's own rules",
        "digest": config.digest(),
        "time_s": {"total_s": time.perf_counter() - t_start},
        "config": config.model_dump(mode="json"),
    }
    return AutoResult(config, reasons, None, None, [], [], costs)


def _kept_acceptance(
    chosen: HierarchyConfig, fitted: HierarchyConfig
) -> tuple[HierarchyConfig, str]:
    """The chosen config with the acceptance it serves with, and where that comes from.

    A bundled preset kept as it ships keeps the models it ships (fitted on real queries of
    every route we have, single frame and sequence): on the routes' test parts they accepted
    more right answers than models fitted on the map's pseudo-queries (single frame 32 won,
    4 lost, pooled) and, unlike the lock rule the pseudo-query fit leaves sequence mode with,
    no foreign frame (``docs/experiments/auto_config/acceptance.md``).

    A hierarchy without shipped models gets the pseudo-query fit (``fitted``) for single
    frames, and for sequence mode the :data:`INCUMBENT` preset's shipped sequence model and
    thresholds (its features are normalised per map; they need a global method in tier 1,
    for the reference profile). Pseudo-queries are no drive, so a sequence model fitted on
    them accepts nothing, and the lock rule accepted 8 % of foreign frames with auto's
    Nordland choice, where the carried model accepted none at precision 0.989
    (``docs/experiments/auto_config/acceptance_found.md``). Without a global tier-1 method
    the lock rule stays.
    """
    shipped = shipped_acceptance()
    own = shipped.get(chosen.digest())
    if own is not None:
        return chosen.model_copy(update={"acceptance": own}), "shipped"
    donor = shipped.get(load_config(INCUMBENT).digest()) if INCUMBENT else None
    acc = fitted.acceptance
    if acc is None or donor is None or donor.sequence_model is None:
        return fitted, "pseudo-queries"
    methods = build_methods(fitted)
    if not any(methods[m].kind == "global" for m in fitted.tiers[0].methods):
        return fitted, "pseudo-queries; sequence: lock rule (no global method in tier 1)"
    carried = acc.model_copy(
        update={
            "sequence_model": donor.sequence_model,
            "sequence_threshold": donor.sequence_threshold,
            "sequence_stay_threshold": donor.sequence_stay_threshold,
            "sequence_stay_ref_z": donor.sequence_stay_ref_z,
        }
    )
    return (
        fitted.model_copy(update={"acceptance": carried}),
        f"pseudo-queries; sequence: the {INCUMBENT} preset's shipped sequence model",
    )


def _transform_kinds(plan_: PseudoPlan) -> dict[str, Any]:
    """How many pseudo-queries carry each kind of change, and a few examples."""
    ts = plan_.transforms
    counts = {
        "exposure": sum(t.gain != 1.0 for t in ts),
        "gamma": sum(t.gamma != 1.0 for t in ts),
        "night": sum(t.night != 1.0 for t in ts),
        "noise": sum(t.noise > 0.0 for t in ts),
        "blur": sum(t.blur > 0.0 for t in ts),
        "crop": sum(t.crop != 1.0 for t in ts),
        "resolution": sum(t.resolution != 1.0 for t in ts),
    }
    return {"counts": counts, "examples": [t.describe() for t in ts[:5]]}


def _acceptance_figures(acc: dict[str, Any], confidence: dict[str, Any] | None) -> dict[str, Any]:
    """The acceptance's pseudo-query figures, without per-answer arrays."""
    out: dict[str, Any] = {"z": acc}
    if confidence is not None:
        out["confidence"] = {
            mode: {k: v for k, v in figs.items() if not isinstance(v, list) or len(v) < 50}
            for mode, figs in confidence.items()
        }
    return out
