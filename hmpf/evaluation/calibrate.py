"""The choice of a hierarchy and its acceptance threshold (layer 4).

The search (:func:`search`) runs on a training split's
:class:`~hmpf.evaluation.study.ScoreBank`, so every tried hierarchy (a :class:`Trial`) is
evaluated on precomputed scores through the real hierarchy code, and on a
:class:`~hmpf.evaluation.study.CostModel` of measured component times, so a per-query time
budget can be enforced. It is deterministic given its seed and cost model:

1. Structures: every tier is a set of 1..``max_per_tier`` pool methods; every 1-tier and
   2-tier structure is tried, and ``samples`` 3-tier structures drawn with the seed (a method
   may reappear in a later tier, as in the paper's "method stacked on itself"), each with the
   middle candidate counts and the default weights.
2. Refinement: the ``refine`` best structures are tried with every candidate count and
   tier-weight combination of the grid.
3. Ranking: Combined recall@1 on the training queries, then the lower modelled time, then
   fewer methods; hierarchies over the budget are left out.

The acceptance threshold (:func:`acceptance_threshold`) is the lowest Combined quality at
which the training answers reach the target precision.

The acceptance of one hierarchy (its z threshold, with sequence mode the filter's settings,
and its confidence models) is fitted by :func:`fit_config_acceptance`, the step
:func:`calibrate` runs for the search's winner and :func:`fit_only` for a given config as it
is (``hmpf-calibrate --config NAME --fit-only``: no search; the config's digest is kept).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hmpf.confidence import ModelError
from hmpf.config import AcceptanceSettings, HierarchyConfig, build_methods
from hmpf.errors import ConfigError
from hmpf.evaluation.acceptance import (
    SEQUENCE_MODEL_FEATURES,
    SINGLE_FEATURES,
    Answers,
    acceptance_figures,
    apply_acceptance,
    carried_terms,
    fit_acceptance,
    outside_answers,
    sequence_answers,
    single_answers,
)
from hmpf.evaluation.metrics import HierarchyOutcome, paired_test, precision_recall_at
from hmpf.evaluation.sequence import format_sequence_report, sequence_settings, training_drives
from hmpf.evaluation.study import (
    CostModel,
    ScoreBank,
    check_compatible,
    derive_config,
    measure_costs,
    measure_query_ms,
)
from hmpf.fusion import default_weights
from hmpf.runtime import machine_description
from hmpf.sequence import FilterParams, RouteMap

__all__ = [
    "AcceptanceFit",
    "SearchSpace",
    "Trial",
    "acceptance_threshold",
    "calibrate",
    "describe",
    "fit_config_acceptance",
    "fit_only",
    "paired_test",
    "precision_recall_at",
    "search",
]

#: Weight of a non-final tier relative to the final tier's 1.
WEIGHT_LADDER = (0.25, 0.5, 0.75, 1.0)


@dataclass(frozen=True)
class SearchSpace:
    """What :func:`search` may choose from.

    Attributes:
        methods: pool method ids.
        max_tiers: 1 to 3.
        max_per_tier: methods per tier (1 or 2 keeps the space searchable).
        k1: candidate counts tier 1 may pass on.
        k2: candidate counts tier 2 may pass on in a 3-tier hierarchy (each < every k1).
        samples: 3-tier structures drawn at random (all are tried when there are fewer).
        refine: structures whose candidate counts and weights are then searched in full.
    """

    methods: tuple[str, ...]
    max_tiers: int = 3
    max_per_tier: int = 2
    k1: tuple[int, ...] = (5, 10, 20)
    k2: tuple[int, ...] = (2, 3, 5)
    samples: int = 1500
    refine: int = 25

    def tier_sets(self) -> list[tuple[str, ...]]:
        out: list[tuple[str, ...]] = []
        for n in range(1, self.max_per_tier + 1):
            out.extend(itertools.combinations(self.methods, n))
        return out


@dataclass
class Trial:
    """One hierarchy the search tried, with its training figures.

    ``recall_at_1`` is -1 and ``model_ms`` infinite for a hierarchy left out over the budget.
    """

    tiers: tuple[tuple[str, ...], ...]
    ks: tuple[int, ...]
    weights: tuple[float, ...]
    recall_at_1: float
    model_ms: float
    tier_top1: list[float] = field(default_factory=list)
    tier_recall: list[float] = field(default_factory=list)
    outcome: HierarchyOutcome | None = None

    @property
    def n_methods(self) -> int:
        return len({m for t in self.tiers for m in t})

    def sort_key(self) -> tuple[Any, ...]:
        return (-self.recall_at_1, self.model_ms, self.n_methods, len(self.tiers), self.label())

    def label(self) -> str:
        return describe(self.tiers, self.ks, self.weights)

    def config(self, pool: HierarchyConfig, name: str = "calibrated") -> HierarchyConfig:
        tiers = [(t, k) for t, k in zip(self.tiers, self.ks, strict=True)]
        return derive_config(pool, tiers, list(self.weights), name=name, description=self.label())

    def to_dict(self) -> dict[str, Any]:
        return {
            "hierarchy": self.label(),
            "tiers": [list(t) for t in self.tiers],
            "k": list(self.ks),
            "weights": list(self.weights),
            "recall_at_1": self.recall_at_1,
            "model_ms": self.model_ms,
            "tier_top1": self.tier_top1,
            "tier_recall": self.tier_recall,
        }


def describe(
    tiers: Sequence[Sequence[str]], ks: Sequence[int], weights: Sequence[float] | None = None
) -> str:
    """``gem+netvlad (10) -> olo (1) [w 0.5/1]``."""
    parts = [f"{'+'.join(t)} ({k})" for t, k in zip(tiers, ks, strict=True)]
    text = " -> ".join(parts)
    if weights is not None and len(tiers) > 1:
        text += " [w " + "/".join(f"{w:g}" for w in weights) + "]"
    return text


def _weight_grid(n: int) -> list[tuple[float, ...]]:
    if n == 1:
        return [(1.0,)]
    if n == 2:
        return [(w, 1.0) for w in WEIGHT_LADDER]
    return [(a, b, 1.0) for a in WEIGHT_LADDER for b in WEIGHT_LADDER if a <= b]


def _k_grid(space: SearchSpace, n: int) -> list[tuple[int, ...]]:
    if n == 1:
        return [(1,)]
    if n == 2:
        return [(k, 1) for k in space.k1]
    return [(a, b, 1) for a in space.k1 for b in space.k2 if b < a]


def _middle(values: Sequence[int]) -> int:
    return sorted(values)[len(values) // 2]


#: Per tier, the pool methods it fuses; tier 1 first.
Structure = tuple[tuple[str, ...], ...]


def _structures(space: SearchSpace, seed: int) -> list[Structure]:
    """The first pass: every 1- and 2-tier structure, ``samples`` 3-tier ones drawn."""
    sets = space.tier_sets()
    structures: list[Structure] = [(s,) for s in sets]
    if space.max_tiers >= 2:
        structures += [(a, b) for a in sets for b in sets]
    if space.max_tiers == 3:
        n3 = len(sets) ** 3
        rng = np.random.default_rng(seed)
        picks: list[int]
        if n3 <= space.samples:
            picks = list(range(n3))
        else:
            picks = sorted(rng.choice(n3, size=space.samples, replace=False).tolist())
        for p in picks:
            a, rest = divmod(int(p), len(sets) ** 2)
            b, c = divmod(rest, len(sets))
            structures.append((sets[a], sets[b], sets[c]))
    return structures


def _middle_counts(space: SearchSpace, n: int) -> tuple[int, ...]:
    """The candidate counts a structure of ``n`` tiers is first tried with."""
    if n == 1:
        return (1,)
    k1 = _middle(space.k1)
    if n == 2:
        return (k1, 1)
    return (k1, max((k for k in space.k2 if k < k1), default=min(space.k2)), 1)


@dataclass
class _Trials:
    """The hierarchies tried so far on ``bank``, each evaluated once."""

    bank: ScoreBank
    pool: HierarchyConfig
    costs: CostModel
    budget_ms: float | None
    seen: dict[tuple[Any, ...], Trial] = field(default_factory=dict)

    def get(self, tiers: Structure, ks: tuple[int, ...], ws: tuple[float, ...]) -> Trial:
        key = (tiers, ks, ws)
        if key not in self.seen:
            self.seen[key] = self._run(tiers, ks, ws)
        return self.seen[key]

    def _run(self, tiers: Structure, ks: tuple[int, ...], ws: tuple[float, ...]) -> Trial:
        cfg = derive_config(self.pool, list(zip(tiers, ks, strict=True)), list(ws))
        budget, costs = self.budget_ms, self.costs
        if budget is not None and costs.query_ms(cfg) > budget:
            # Over budget even at the upper bound of later tiers' inputs? Check the real sizes.
            if costs.query_ms(cfg, _min_inputs(cfg, costs.n_db)) > budget:
                return Trial(tiers, ks, ws, -1.0, float("inf"))
        out = self.bank.run(cfg)
        model_ms = costs.query_ms(cfg, out.mean_inputs)
        return Trial(tiers, ks, ws, out.recall_at_1, model_ms, out.tier_top1, out.tier_recall, out)

    def ranked(self) -> list[Trial]:
        """The trials within the budget, best first."""
        return sorted(_within(self.seen.values(), self.budget_ms), key=Trial.sort_key)


def search(
    bank: ScoreBank,
    pool: HierarchyConfig,
    costs: CostModel,
    space: SearchSpace,
    *,
    budget_ms: float | None = None,
    seed: int = 0,
    progress: Callable[[int, int], Any] | None = None,
) -> list[Trial]:
    """Every hierarchy tried, best first (see the module docstring); over-budget ones dropped.

    Args:
        progress: optional callable ``(done, total)`` for long searches; ``total`` grows
            once, when the first pass has chosen the structures to refine.
    """
    if not 1 <= space.max_tiers <= 3:
        raise ValueError("max_tiers must be 1, 2 or 3")
    if not space.k1 or (space.max_tiers == 3 and not space.k2):
        raise ValueError("candidate counts k1 (and k2 for 3 tiers) must not be empty")
    trials = _Trials(bank, pool, costs, budget_ms)
    structures = _structures(space, seed)
    total = len(structures)
    for i, st in enumerate(structures):
        trials.get(st, _middle_counts(space, len(st)), default_weights(len(st)))
        if progress is not None:
            progress(i + 1, total)
    best_structures: list[Structure] = []
    for trial in trials.ranked():
        if trial.tiers not in best_structures:
            best_structures.append(trial.tiers)
        if len(best_structures) >= space.refine:
            break
    grid = [
        (st, kg, ws)
        for st in best_structures
        for kg in _k_grid(space, len(st))
        for ws in _weight_grid(len(st))
    ]
    for j, (st, kg, ws) in enumerate(grid):
        trials.get(st, kg, ws)
        if progress is not None:
            progress(total + j + 1, total + len(grid))
    return trials.ranked()


def _within(trials: Any, budget_ms: float | None) -> list[Trial]:
    return [
        t for t in trials if t.recall_at_1 >= 0 and (budget_ms is None or t.model_ms <= budget_ms)
    ]


def _min_inputs(cfg: HierarchyConfig, n_db: int) -> list[float]:
    """Smallest possible references per tier (a later tier scores at least its k sources)."""
    out = [float(n_db)]
    for t in range(1, len(cfg.tiers)):
        out.append(float(min(n_db, cfg.tiers[t - 1].k)))
    return out


# -- acceptance -------------------------------------------------------------------------------


def acceptance_threshold(
    quality: np.ndarray, correct: np.ndarray, target: float = 0.99
) -> dict[str, Any]:
    """The lowest quality threshold whose accepted answers reach ``target`` precision.

    An answer is accepted when its quality is >= the threshold (as the service's
    ``accepted``). Thresholds are the observed qualities; the lowest one whose accepted set
    has precision >= ``target`` wins (the most answers at that precision). When even the
    single best-scored answer is wrong, nothing can be accepted: the threshold is then just
    above the highest quality seen, and ``reached`` is False.
    """
    q = np.nan_to_num(np.asarray(quality, np.float64), nan=-np.inf)
    c = np.asarray(correct, bool)
    order = np.argsort(-q, kind="stable")
    qs, cs = q[order], c[order]
    best: float | None = None
    for i in range(len(qs)):
        # Accepting everything >= qs[i] includes all ties of qs[i].
        if i + 1 < len(qs) and qs[i + 1] == qs[i]:
            continue
        if not np.isfinite(qs[i]):
            break
        prec = cs[: i + 1].mean()
        if prec >= target:
            best = float(qs[i])
    finite = q[np.isfinite(q)]
    if best is None:
        top = float(finite.max()) if finite.size else 0.0
        threshold = float(np.nextafter(top, np.inf))
        reached = False
    else:
        threshold = best
        reached = True
    stats = precision_recall_at(q, c, threshold)
    return {"threshold": threshold, "target": target, "reached": reached, **stats}


# -- the whole procedure ----------------------------------------------------------------------


def compare_on(bank: ScoreBank, pool: HierarchyConfig, config: HierarchyConfig) -> dict[str, Any]:
    """A hierarchy against its best single method and flat fusion of its methods, on a bank
    built from ``pool`` (the hierarchy's methods must have the pool's settings), with a paired
    sign test against each (:func:`paired_test`)."""
    check_compatible(config, pool)
    out = bank.run(config)
    singles = {m: bank.single_recall(m, [1])[1] for m in config.method_ids}
    best = max(singles, key=lambda m: (singles[m], m))
    flat_cfg = derive_config(pool, [(config.method_ids, 1)], None, name="flat")
    flat = bank.run(flat_cfg)
    single_correct = bank.single_correct(best)
    return {
        "recall_at_1": out.recall_at_1,
        "tier_top1": out.tier_top1,
        "tier_recall": out.tier_recall,
        "single": singles,
        "best_single": best,
        "best_single_recall_at_1": singles[best],
        "flat_recall_at_1": flat.recall_at_1,
        "vs_best_single": paired_test(out.correct, single_correct),
        "vs_flat": paired_test(out.correct, flat.correct),
        "outcome": out,
    }


def _z_acceptance(
    outcome: HierarchyOutcome, target_precision: float
) -> tuple[AcceptanceSettings, dict[str, Any]]:
    """The acceptance by the Combined z threshold of a hierarchy's training answers, and the
    threshold's figures (:func:`acceptance_threshold`)."""
    acc = acceptance_threshold(outcome.quality, outcome.correct, target_precision)
    note = (
        f"lowest Combined quality giving {target_precision:.0%} precision on the training "
        f"split ({acc['n_accepted']} of {acc['n_queries']} answers accepted)"
        if acc["reached"]
        else f"no threshold reached {target_precision:.0%} precision on the training split: "
        "nothing is accepted"
    )
    acceptance = AcceptanceSettings(
        threshold=round(acc["threshold"], 6), precision=target_precision, note=note
    )
    return acceptance, acc


@dataclass
class AcceptanceFit:
    """A hierarchy's acceptance fitted on a training part (:func:`fit_config_acceptance`).

    Attributes:
        config: the hierarchy with its ``acceptance`` (and, in sequence mode, its
            ``sequence``) replaced (keeping what :func:`fit_config_acceptance` says it
            keeps); everything else as given, so its digest is unchanged.
        acceptance: the z threshold's training figures (:func:`acceptance_threshold`).
        sequence_params: the sequence filter's chosen settings (sequence mode), or None.
        sequence: their training figures (sequence mode), or None.
        confidence: the confidence models' training figures, or None without models.
    """

    config: HierarchyConfig
    acceptance: dict[str, Any]
    sequence_params: FilterParams | None = None
    sequence: dict[str, Any] | None = None
    confidence: dict[str, Any] | None = None


def fit_config_acceptance(
    config: HierarchyConfig,
    train: ScoreBank,
    *,
    target_precision: float = 0.99,
    seed: int = 0,
    sequence: bool = False,
    model: bool = True,
    outside: bool = True,
    outcome: HierarchyOutcome | None = None,
) -> AcceptanceFit:
    """Fit ``config``'s acceptance on the training part ``train`` (a bank holding its
    methods): the step the search runs for its winner, and ``--fit-only`` for a given config.

    The z threshold is the lowest Combined quality reaching ``target_precision`` on the
    training answers (:func:`acceptance_threshold`); with ``sequence`` the sequence filter's
    settings and lock threshold are chosen too (from the config's own ``sequence:`` as the
    base; written as ``sequence:``); with ``model`` the confidence models are fitted
    (:func:`_fit_models`, with ``outside`` on the training part's out-of-map answers too).
    Any acceptance the config had is replaced, but for what one route cannot teach: its
    single-frame model's staged off-map hinges (:func:`~hmpf.evaluation.acceptance.carried_terms`;
    not without ``outside``) and, with ``sequence``, its stay threshold and evidence floor
    (:func:`_carry_stay`), which the fitted models keep.

    Args:
        outcome: ``config``'s outcome on ``train`` when already known (the search's trial).
    """
    missing = [m for m in config.method_ids if m not in train.methods]
    if missing:
        raise ConfigError(f"the training bank does not hold {', '.join(missing)}")
    other = _other_settings(config, train)
    if other:
        raise ConfigError(
            f"the training bank's {', '.join(other)} scored with other settings than "
            f"{config.name!r}'s; build the banks from this config (or a pool with its settings)"
        )
    if outcome is None:
        outcome = train.run(config)
    given = config.acceptance
    # The given model's off-map hinges, fitted on frames a route's training part lacks.
    carried = carried_terms(given) if outside else {}
    acceptance, acc = _z_acceptance(outcome, target_precision)
    config = config.model_copy(update={"acceptance": acceptance})
    fit = AcceptanceFit(config, acc)
    if sequence:
        fit.sequence_params, fit.sequence = train.tune_sequence(
            config, target_precision=target_precision, seed=seed
        )
        fit.config = config.model_copy(update={"sequence": sequence_settings(fit.sequence_params)})
    if model:
        fit.config, fit.confidence = _fit_models(
            fit.config, train, target_precision, fit.sequence_params, outside=outside,
            carried=carried, stay_from=given,
        )  # fmt: skip
    return fit


def _carry_stay(
    config: HierarchyConfig, given: AcceptanceSettings | None, figures: dict[str, Any]
) -> HierarchyConfig:
    """``config`` with the given acceptance's sequence stay threshold (at most the fitted
    entry threshold) and its evidence floor, where both have a sequence model; noted in
    ``figures["sequence"]["stay"]``.

    Why carry them: without a stay threshold an estimate that stays right is accepted on
    one frame and not the next as its probability wavers about the entry threshold (a
    route's own models: 15-30 flips per 100 frames on the Gardens Point training drives);
    the shipped one (0.9, floor -0.5) was chosen across routes with drives that leave the
    map (bench/shipped_acceptance.py, bench/stay_rule.py), which one route's training
    part cannot do (docs/calibration.md)."""
    acc = config.acceptance
    if (
        acc is None
        or acc.sequence_model is None
        or acc.sequence_threshold is None
        or given is None
        or given.sequence_stay_threshold is None
    ):
        return config
    stay = min(given.sequence_stay_threshold, acc.sequence_threshold)
    floor = given.sequence_stay_ref_z
    figures.setdefault("sequence", {})["stay"] = {"threshold": stay, "ref_z": floor}
    acc = acc.model_copy(update={"sequence_stay_threshold": stay, "sequence_stay_ref_z": floor})
    acc = AcceptanceSettings.model_validate(acc.model_dump())
    return config.model_copy(update={"acceptance": acc})


#: Method settings that do not change a method's scores (where and how many at once).
_RUNNING = {"device", "batch_size"}


def _other_settings(config: HierarchyConfig, bank: ScoreBank) -> list[str]:
    """The methods of ``config`` that ``bank`` holds with other settings (its instances were
    built from another spec under the same id: their scores are not this config's)."""
    fresh = build_methods(config)  # settings only: nothing is loaded or fitted

    def settings(m: Any) -> Any:
        return m.config.model_copy(update={k: None for k in _RUNNING if hasattr(m.config, k)})

    return [
        mid
        for mid in config.method_ids
        if type(bank.methods[mid]) is not type(fresh[mid])
        or settings(bank.methods[mid]) != settings(fresh[mid])
    ]


def _train_figures(fit: AcceptanceFit) -> dict[str, Any]:
    """The acceptance's training figures as the report's ``train`` entries."""
    out: dict[str, Any] = {"acceptance": fit.acceptance}
    if fit.sequence is not None:
        out["sequence"] = fit.sequence
    if fit.confidence is not None:
        out["confidence"] = fit.confidence
    return out


def _test_figures(
    fit: AcceptanceFit,
    pool: HierarchyConfig,
    test: ScoreBank,
    *,
    seed: int = 0,
    costs: CostModel | None = None,
) -> dict[str, Any]:
    """The fitted hierarchy on the test part: against its best single method and flat
    fusion (:func:`compare_on`), its answers at the training thresholds, its measured (and,
    with ``costs``, modelled) time per query, sequence mode and the models' figures."""
    config = fit.config
    cmp = compare_on(test, pool, config)
    out = cmp.pop("outcome")
    report: dict[str, Any] = {
        "n_reference": test.n_db,
        "n_query": test.n_query,
        **cmp,
        "acceptance": precision_recall_at(out.quality, out.correct, fit.acceptance["threshold"]),
        "measured_ms": measure_query_ms(config, test),
    }
    if costs is not None:
        report["model_ms"] = costs.query_ms(config, out.mean_inputs)
    if fit.sequence_params is not None:
        report["sequence"] = test.sequence(config, fit.sequence_params, seed=seed)
    if fit.confidence is not None:
        report["confidence"] = _test_models(config, test, fit.sequence_params)
    return report


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


def calibrate(
    pool: HierarchyConfig,
    train: ScoreBank,
    test: ScoreBank | None,
    space: SearchSpace,
    *,
    budget_ms: float | None,
    seed: int = 0,
    target_precision: float = 0.99,
    db_size: int | None = None,
    name: str = "calibrated",
    top: int = 20,
    progress: Callable[[int, int], Any] | None = None,
    costs: CostModel | None = None,
    sequence: bool = False,
    model: bool = True,
    outside: bool = True,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """Search, pick the threshold, check on the test part; returns (config, report).

    The winner's acceptance is fitted by :func:`fit_config_acceptance`. With ``model``
    (default), the confidence models are fitted on the training part too
    (:func:`_fit_models`): ``acceptance.model`` / ``model_threshold`` and, with
    ``sequence``, ``sequence_model`` / ``sequence_threshold``; the z threshold stays (the
    fallback for a reader without a model). With ``outside`` (default) the models also learn
    from the training part's own out-of-map answers
    (:func:`~hmpf.evaluation.acceptance.outside_answers`). The report's ``confidence``
    entries (training and test) give the ECE, accepted share and precision of the model and
    of the z rule.

    With ``sequence``, the sequence filter's settings and lock threshold are chosen for the
    winner on the training part too (written as the config's ``sequence:``) and its
    sequence-mode figures measured on the test part.

    Args:
        db_size: charge tier 1 for this many references (default: the training split's).
        costs: a fixed cost model (e.g. :meth:`CostModel.from_dict` of an earlier report's
            ``costs``) instead of one measured on this machine: the search then chooses the
            same hierarchy on any machine.
    """
    t0 = time.perf_counter()
    if costs is None:
        costs = measure_costs(train, n_db=db_size)
    elif db_size is not None:
        costs = replace(costs, n_db=db_size)
    ranked = search(train, pool, costs, space, budget_ms=budget_ms, seed=seed, progress=progress)
    if not ranked:
        raise ConfigError(
            f"no hierarchy of the pool fits the budget of {budget_ms:g} ms per query "
            f"(cheapest extraction: {min(costs.units.values()):.1f} ms); raise --budget-ms"
        )
    search_s = time.perf_counter() - t0
    win = ranked[0]
    fit = fit_config_acceptance(
        win.config(pool, name=name),
        train,
        target_precision=target_precision,
        seed=seed,
        sequence=sequence,
        model=model,
        outside=outside,
        outcome=win.outcome,
    )
    report: dict[str, Any] = {
        "mode": "search",
        "machine": machine_description(),
        "seed": seed,
        "budget_ms": budget_ms,
        "space": _space_dict(space),
        "costs": costs.to_dict(),
        "evaluated": len(ranked),
        "search_s": search_s,
        "train": {
            "n_reference": train.n_db,
            "n_query": train.n_query,
            "winner": win.to_dict(),
            "leaderboard": [t.to_dict() for t in ranked[:top]],
            **_train_figures(fit),
        },
        "config": fit.config.model_dump(mode="json"),
    }
    if test is not None:
        report["test"] = _test_figures(fit, pool, test, seed=seed, costs=costs)
    return fit.config, report


def fit_only(
    config: HierarchyConfig,
    train: ScoreBank,
    test: ScoreBank | None,
    *,
    seed: int = 0,
    target_precision: float = 0.99,
    sequence: bool = False,
    model: bool = True,
    outside: bool = True,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """Fit the acceptance of ``config`` as it is (no search) and check it on the test part;
    returns (config, report), as :func:`calibrate` but for a given hierarchy.

    The banks must hold the config's methods (built from ``config`` itself, or from a pool
    with the same settings). The returned config is ``config`` with its acceptance (with
    ``sequence``, also its ``sequence:``) replaced by :func:`fit_config_acceptance`: its
    digest, which ignores both, is the input's. The test part is measured as the search's
    winner's is (no cost model: no modelled time).
    """
    t0 = time.perf_counter()
    outcome = train.run(config)
    fit = fit_config_acceptance(
        config,
        train,
        target_precision=target_precision,
        seed=seed,
        sequence=sequence,
        model=model,
        outside=outside,
        outcome=outcome,
    )
    hierarchy = describe(
        [t.methods for t in config.tiers], [t.k for t in config.tiers], config.tier_weights
    )
    report: dict[str, Any] = {
        "mode": "fit-only",
        "machine": machine_description(),
        "seed": seed,
        "digest": fit.config.digest(),
        "fit_s": time.perf_counter() - t0,
        "train": {
            "n_reference": train.n_db,
            "n_query": train.n_query,
            "hierarchy": hierarchy,
            "recall_at_1": outcome.recall_at_1,
            "tier_top1": outcome.tier_top1,
            "tier_recall": outcome.tier_recall,
            **_train_figures(fit),
        },
        "config": fit.config.model_dump(mode="json"),
    }
    if test is not None:
        report["test"] = _test_figures(fit, config, test, seed=seed)
    return fit.config, report


def _fit_models(
    config: HierarchyConfig,
    train: ScoreBank,
    target_precision: float,
    seq_params: FilterParams | None,
    *,
    outside: bool = True,
    carried: Mapping[str, float] | None = None,
    stay_from: AcceptanceSettings | None = None,
) -> tuple[HierarchyConfig, dict[str, Any]]:
    """``config`` with its confidence models fitted on the training part, and their
    training figures (:mod:`hmpf.evaluation.acceptance`); with ``outside``, with the
    training part's own out-of-map answers; ``carried``: terms the single-frame model
    keeps as they are (:func:`~hmpf.evaluation.acceptance.carried_terms`); ``stay_from``:
    the acceptance whose stay threshold the sequence model keeps (:func:`_carry_stay`),
    with the training drives' figures as the policy then decides them (``as_decided``:
    the threshold is chosen frame by frame, without it)."""
    assert config.acceptance is not None
    routes = RouteMap.from_metadata(train.n_db)
    results = train.results(config)
    profile = train.profile(config)
    update: dict[str, Any] = {}
    out: dict[str, Any] = {}
    # Answers to places the map does not hold, from the training part itself.
    out_single: Answers | None = None
    out_seq: Answers | None = None
    if outside:
        out_single, out_seq = outside_answers(train, config, profile, seq_params)
    modes: list[tuple[str, tuple[str, ...], Answers, Answers | None]] = [
        ("single", SINGLE_FEATURES, single_answers(results, train.gt, routes, profile), out_single)
    ]
    if seq_params is not None:
        drives = training_drives(train.n_query)
        seq = sequence_answers(results, train.gt, routes, seq_params, drives, profile)
        modes.append(("sequence", SEQUENCE_MODEL_FEATURES, seq, out_seq))
    for mode, names, answers, negatives in modes:
        keep = dict(carried or {}) if mode == "single" else {}
        try:
            m, thr, figs = fit_acceptance(answers, names, target_precision, negatives, carried=keep)
        except ModelError as e:
            # No model for this mode: the z (or mass) rule decides, and the report says why.
            out[mode] = {"features": list(names), "skipped": str(e)}
            continue
        key, thr_key = (
            ("model", "model_threshold")
            if mode == "single"
            else ("sequence_model", "sequence_threshold")
        )
        update |= {key: m.to_dict(), thr_key: thr}
        out[mode] = {"features": list(names), **figs}
        if keep:
            out[mode]["carried"] = keep
    acceptance = config.acceptance.model_copy(update=update)
    # Validate as a config read from disk would be.
    acceptance = AcceptanceSettings.model_validate(acceptance.model_dump())
    config = _carry_stay(config.model_copy(update={"acceptance": acceptance}), stay_from, out)
    if seq_params is not None and "stay" in out.get("sequence", {}):
        decided = apply_acceptance(
            config.acceptance, seq, sequence=True, lock_mass=seq_params.lock_mass
        )
        out["sequence"]["stay"]["as_decided"] = _figures(decided)
    return config, out


def _test_models(
    config: HierarchyConfig, test: ScoreBank, seq_params: FilterParams | None
) -> dict[str, Any]:
    """The model's and the z rule's figures on the test part at the training thresholds
    (sequence mode: the test part's queries driven once, in order; model against the
    posterior mass >= the lock threshold)."""
    routes = RouteMap.from_metadata(test.n_db)
    results = test.results(config)
    profile = test.profile(config)
    single = single_answers(results, test.gt, routes, profile)
    out: dict[str, Any] = {
        "single": {
            "model": _figures(apply_acceptance(config.acceptance, single)),
            "z": acceptance_figures(
                single.score, single.correct, config.acceptance.threshold, probability=False
            )
            if config.acceptance is not None
            else None,
        }
    }
    if seq_params is not None:
        seq = sequence_answers(results, test.gt, routes, seq_params, profile=profile)
        out["sequence"] = {
            "model": _figures(
                apply_acceptance(
                    config.acceptance, seq, sequence=True, lock_mass=seq_params.lock_mass
                )
            ),
            "mass": acceptance_figures(
                seq.score, seq.correct, seq_params.lock_mass, probability=False
            ),
        }
    return out


def _figures(applied: dict[str, Any]) -> dict[str, Any]:
    per_answer = ("p_correct", "accepted_answers", "off_map")
    return {k: v for k, v in applied.items() if k not in per_answer}


def leaderboard_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown: leaderboard (or, fit-only, the given hierarchy), threshold
    and the test check."""
    head = _fit_only_head(report) if report.get("mode") == "fit-only" else _search_head(report)
    return "\n".join([*head, *_acceptance_lines(report), *_test_lines(report)]) + "\n"


def _search_head(report: dict[str, Any]) -> list[str]:
    """The search's summary and its leaderboard."""
    tr = report["train"]
    lines = [
        f"# Calibration ({report['machine']})",
        "",
        f"Seed {report['seed']}, budget {report['budget_ms']} ms per query (modelled from "
        f"measured parts, one compute thread), {report['evaluated']} hierarchies within the "
        f"budget evaluated on {tr['n_query']} training queries against {tr['n_reference']} "
        f"references in {report['search_s']:.0f} s.",
        "",
        "| rank | hierarchy | train recall@1 | modelled ms/query |",
        "|---|---|---|---|",
    ]
    for i, c in enumerate(tr["leaderboard"], start=1):
        lines.append(f"| {i} | {c['hierarchy']} | {c['recall_at_1']:.3f} | {c['model_ms']:.1f} |")
    return lines


def _fit_only_head(report: dict[str, Any]) -> list[str]:
    """What a fit-only run fitted: the given hierarchy, no search."""
    tr = report["train"]
    return [
        f"# Acceptance fit, no search ({report['machine']})",
        "",
        f"Fit only: the acceptance of the given hierarchy {tr['hierarchy']} (config digest "
        f"{report['digest'][:16]}, unchanged), fitted on {tr['n_query']} training queries "
        f"against {tr['n_reference']} references (training recall@1 "
        f"{tr['recall_at_1']:.3f}) in {report['fit_s']:.0f} s; seed {report['seed']}.",
    ]


def _acceptance_lines(report: dict[str, Any]) -> list[str]:
    """The z threshold, the sequence filter's choice and the confidence models."""
    tr = report["train"]
    acc = tr["acceptance"]
    lines = [
        "",
        f"Acceptance threshold {acc['threshold']:.3f} (target precision {acc['target']:.0%}, "
        f"{'reached' if acc['reached'] else 'NOT reached'} on training: precision "
        f"{_fmt(acc['precision'])}, recall {acc['recall']:.3f}).",
    ]
    if tr.get("sequence"):
        lines += [
            "",
            f"Sequence filter chosen on the training drives ({len(tr['sequence']['grid'])} "
            f"settings): lock threshold {tr['sequence']['lock_mass']:.3f} for "
            f"{tr['sequence']['target_precision']:.0%} precision.",
        ]
    return lines + _confidence_lines(report)


def _test_lines(report: dict[str, Any]) -> list[str]:
    """The test part's sequence mode and its check against single methods and flat fusion."""
    te = report.get("test")
    if not te:
        return []
    lines: list[str] = []
    if te.get("sequence"):
        lines += ["", "Sequence mode on the test split:", "", "```"]
        lines += [*format_sequence_report(te["sequence"]), "```"]
    ta = te["acceptance"]
    modelled = f" (modelled {te['model_ms']:.1f})" if "model_ms" in te else ""
    lines += [
        "",
        f"Test split ({te['n_query']} queries, {te['n_reference']} references): "
        f"calibrated recall@1 {te['recall_at_1']:.3f}, best single method "
        f"({te['best_single']}) {te['best_single_recall_at_1']:.3f}, flat fusion of its "
        f"methods {te['flat_recall_at_1']:.3f} (queries won/lost against them "
        f"{_wl(te['vs_best_single'])} and {_wl(te['vs_flat'])}); at the threshold precision "
        f"{_fmt(ta['precision'])}, recall {ta['recall']:.3f}; "
        f"{te['measured_ms']['total_ms']:.1f} ms per query measured end to end{modelled}.",
    ]
    return lines


def _confidence_lines(report: dict[str, Any]) -> list[str]:
    """The confidence models' thresholds and their test figures beside the z rule's."""
    tr = report["train"].get("confidence")
    if not tr:
        return []
    te = (report.get("test") or {}).get("confidence") or {}
    lines = [
        "",
        "Confidence models (fitted on the training part; thresholds from out-of-fold "
        "training predictions):",
        "",
        "| mode | rule | threshold | test ECE | test accepted | test precision |",
        "|---|---|---|---|---|---|",
    ]
    for mode, base in (("single", "z"), ("sequence", "mass")):
        if mode not in tr:
            continue
        if "skipped" in tr[mode]:
            lines.append(f"| {mode} | model not fitted: {tr[mode]['skipped']} | | | | |")
        t = te.get(mode) or {}
        for rule in ("model", base):
            f = t.get(rule)
            if f is None:
                thr = tr[mode]["threshold"] if rule == "model" else None
                lines.append(f"| {mode} | {rule} | {_fmt(thr)} | n/a | n/a | n/a |")
                continue
            lines.append(
                f"| {mode} | {rule} | {f['threshold']:.4g} | {_fmt(f.get('ece'))} | "
                f"{f['accepted']:.3f} | {_fmt(f['precision'])} |"
            )
    stay = tr.get("sequence", {}).get("stay")
    if stay:
        floor = "" if stay["ref_z"] is None else f", evidence floor {stay['ref_z']:g}"
        lines += [
            "",
            f"The sequence model keeps the given config's stay threshold: "
            f"{stay['threshold']:.3f}{floor} (hysteresis, chosen across routes).",
        ]
        if stay.get("as_decided"):
            d = stay["as_decided"]
            lines[-1] += (
                f" With it the training drives' answers are accepted {d['accepted']:.3f} at "
                f"precision {_fmt(d['precision'])} (the threshold was chosen without it)."
            )
    carried = tr.get("single", {}).get("carried")
    if carried:
        terms = ", ".join(f"{n} {c:.3f}" for n, c in carried.items())
        lines += [
            "",
            f"The single-frame model keeps the given config's off-map terms as they were "
            f"({terms}): fitted on frames of other data sets, which a route's training part "
            "does not have.",
        ]
    return lines


def _wl(t: dict[str, Any]) -> str:
    return f"{t['wins']}/{t['losses']}, sign test p = {t['p']:.2g}"


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"
