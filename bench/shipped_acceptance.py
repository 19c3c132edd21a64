"""The confidence models a bundled preset ships: fitted on every route we have, checked on
routes they never saw.

    python -m bench.shipped_acceptance [--config default] [--foreign 200] [--write]
        [--[no-]map-prior] [--stay X] [--stay-ref-z Z|none] [--gate single,sequence|none]
        [--single-share S] [--single-extra F,...] [--out results/shipped_acceptance_default.json]

Each route (Gardens Point's three protocols, Nordland summer -> winter; all with the same
preset) is split as ``hmpf-calibrate`` splits it (alternating stretches of 20 frames). On the
*training* parts, pooled with each route weighing alike (:func:`fit_pooled`):

* the single-frame model (:data:`SINGLE_FEATURES`) and the sequence model
  (:data:`SEQUENCE_FEATURES`), each trained with the route's own out-of-map answers
  (:func:`outside_answers`: each stretch of queries answered with its references removed);
  and each route's frames of *another data set* against its map (Nordland summer for the
  Gardens Point maps, Gardens Point day_left for Nordland: never the frames tested below);
* their thresholds for 99 % precision, chosen on out-of-fold predictions (five stretches
  of consecutive queries per route, :func:`route_out_of_fold`); bounding them by the
  out-of-map answers (at most 1 % accepted) left the night routes' sequence mode at 2-4 %
  accepted, so the off-map answers shape the model and the filter's off state, not the
  threshold;
* the sequence model's stay threshold (hysteresis, ``--stay``) and whether both models read
  the map's prior (``--map-prior``): by default the recipe the preset's shipped models were
  fitted with (:func:`shipped_recipe`; ``default``: the prior and 0.9, since 2026-11-29), so
  ``--write`` refits them as they are; a preset without shipped models:
  :data:`hmpf.acceptance.STAY_P` and no prior. ``--stay-ref-z``: the stay threshold's
  evidence floor (``sequence_stay_ref_z``; ``default`` since 2026-12-07:
  :data:`hmpf.acceptance.STAY_REF_Z`, chosen by ``bench/stay_rule.py``). ``--gate``,
  ``--single-share`` and ``--single-extra`` try other recipes (a gated model,
  :meth:`~hmpf.confidence.ConfidenceModel.fit_gated`; the single-frame model's share of
  off-map answers; features added to it), also recorded in the recipe.

Then, per held-out route (**leave one route out**: the models fitted on the other routes
only) and for the shipped fit (all routes), on the route's *test* part:

* in the map: the share of single-frame and sequence answers accepted, their precision,
  the sequence model's ECE, lock flips per 100 frames on the drive (accepted -> not or back,
  after the first acceptance) and the sequence recall@1;
* off the map: ``--foreign`` frames of another data set (Nordland winter against the
  Gardens Point maps, Gardens Point night_right against the Nordland map), single frame and
  driven in order in sequence mode: the share accepted and the mean ``p_correct``;
* a drive that leaves the map and comes back (40 in-map frames, 60 foreign frames, the rest
  of the test part): accepted frames while away, frames until the first acceptance after
  coming back.

The Gardens Point protocols share traverses (day_right, night_right appear in two each), so a
held-out Gardens Point protocol is not a new place; the Nordland fold is (another country,
camera and season). With ``--write`` the shipped fit goes to
``hmpf/presets/acceptance/<config>.json`` (with the hierarchy's digest, which
:func:`hmpf.config.with_shipped_acceptance` matches).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from bench.harness import ROOT, Parser, add_json, parser, provenance, write_json, write_record
from hmpf.acceptance import SINGLE_MODEL_FEATURES, STAY_P, Policy
from hmpf.confidence import ConfidenceModel, ReferenceProfile, expected_calibration_error
from hmpf.config import AcceptanceSettings, HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images
from hmpf.evaluation.acceptance import (
    SINGLE_FEATURES,
    Answers,
    RoutePart,
    apply_acceptance,
    concat_answers,
    decide,
    fit_pooled,
    outside_answers,
    route_out_of_fold,
    sequence_answers,
    single_answers,
)
from hmpf.evaluation.auto import map_prior
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.sequence import Drive, training_drives
from hmpf.evaluation.study import ScoreBank, split_data
from hmpf.features import FeatureCache
from hmpf.runtime import default_cache_dir
from hmpf.sequence import FilterParams, RouteMap

#: Route name -> (reference folder, query folder, the foreign frames' folder for the test,
#: the foreign frames' folder for training: other frames of another data set).
ROUTES = {
    **{
        k: (r, q, "nordland_64x32/winter", "nordland_64x32/summer")
        for k, (r, q) in GARDENS_POINT_PROTOCOLS.items()
    },
    "nordland_s_w": (
        "nordland_64x32/summer",
        "nordland_64x32/winter",
        "gardens_point/night_right",
        "gardens_point/day_left",
    ),
}
#: Nordland's first frames used: 800 (400 per part) keep a run within the two cores' hour
#: with the default's CNN passes over 64 x 32 thumbnails; ``--nordland-frames 0``: all.
NORDLAND_FRAMES = 800
#: Foreign training frames per map (spread over their folder, offset from the test's).
TRAIN_FOREIGN = 100
#: The sequence model's features: the estimate's log-odds, its absolute evidence, whether
#: it agrees with the single-frame answer, and the frame's own single-frame evidence.
SEQUENCE_FEATURES = ("sequence_logit", "sequence_ref_z", "sequence_agrees", "ref_z")
TARGET = 0.99
#: Weight of a route's off-map training answers, as a share of all its answers: the models'
#: ``p_correct`` is for a stream of frames of which this share comes from off the map.
OFF_SHARE = float(os.environ.get("HMPF_OFF_SHARE", "0.1"))
TOLERANCE = 2
BLOCK = 20
#: The leave-and-return drive: in-map frames, then foreign frames, then the rest in-map.
AWAY = (40, 60)


def spread(n: int, count: int) -> np.ndarray:
    """``count`` indices spread evenly over ``range(n)`` (all when ``count >= n``)."""
    if count >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, count).round().astype(np.int64))


class Route:
    """One route's banks: training part, and test part with foreign frames appended."""

    def __init__(
        self,
        name: str,
        config: HierarchyConfig,
        cache: FeatureCache,
        foreign: int,
        limit: int | None = None,
        map_prior: float | None = None,
    ) -> None:
        ref, qry, other, train_other = ROUTES[name]
        root = dataset_root()
        data = EvalData.frames(root / ref, root / qry, TOLERANCE)
        if limit is not None and limit < len(data.reference):  # the route's first frames
            data = EvalData(
                data.reference[:limit], data.query[:limit], data.gt[:limit, :limit],
                data.ground_truth,
            )  # fmt: skip
        train, test = split_data(data, block=BLOCK)
        frames = list_images(root / other)
        away = [frames[i] for i in spread(len(frames), foreign)]
        gt = np.vstack([test.gt, np.zeros((len(away), len(test.reference)), bool)])
        both = EvalData(test.reference, [*test.query, *away], gt, test.ground_truth)
        t_frames = list_images(root / train_other)
        # offset by half a step from the test's spread (another data set's other frames)
        t_away = [
            t_frames[min(len(t_frames) - 1, i + 3)] for i in spread(len(t_frames), TRAIN_FOREIGN)
        ]
        t_gt = np.vstack([train.gt, np.zeros((len(t_away), len(train.reference)), bool)])
        t_both = EvalData(train.reference, [*train.query, *t_away], t_gt, train.ground_truth)
        self.name = name
        #: The route's frames used, and its training and test parts (without foreign frames).
        self.data, self.train_data, self.test_data = data, train, test
        self.train = ScoreBank.build(config, t_both, cache=cache)
        self.n_train = len(train.query)
        self.test = ScoreBank.build(config, both, cache=cache)
        self.n_test = len(test.query)
        self.n_foreign = len(away)
        self.config = config
        #: The map's prior (:func:`route_prior`), given to every bank's profile and so to
        #: every answer's features; None: unknown (no model here reads it).
        self.map_prior = map_prior
        self.train.map_prior = self.test.map_prior = map_prior
        self._cache = cache
        self._whole: ScoreBank | None = None
        self._whole_answers: tuple[list[Any], ReferenceProfile] | None = None

    def whole(self) -> ScoreBank:
        """The bank of the route's whole traverse (every reference, every query, in order:
        no stretch joined to another), built on first use."""
        if self._whole is None:
            self._whole = ScoreBank.build(self.config, self.data, cache=self._cache)
            self._whole.map_prior = self.map_prior
        return self._whole

    def whole_results(self) -> tuple[list[Any], ReferenceProfile]:
        """The hierarchy's results on the whole traverse and its map's profile, computed
        once (every policy reads the same answers)."""
        if self._whole_answers is None:
            bank = self.whole()
            self._whole_answers = (bank.results(self.config), bank.profile(self.config))
        return self._whole_answers


def limit_of(name: str, nordland_frames: int) -> int | None:
    """The frames of route ``name`` used (None: all)."""
    return nordland_frames or None if name.startswith("nordland") else None


def training_part(route: Route, params: FilterParams) -> tuple[RoutePart, RoutePart]:
    """The route's single-frame and sequence training answers, each with its out-of-map
    ones (:func:`outside_answers` and frames of another data set); with the route's
    :attr:`Route.map_prior` in every answer's features (through the bank's profile)."""
    full, config = route.train, route.config
    nq = route.n_train
    bank = full.rows(np.arange(nq))
    routes = RouteMap.from_metadata(bank.n_db)
    all_results = full.results(config)
    results = all_results[:nq]
    profile = bank.profile(config)
    single = single_answers(results, bank.gt, routes, profile)
    drives = sequence_answers(results, bank.gt, routes, params, training_drives(nq), profile)
    out_single, out_seq = outside_answers(bank, config, profile, params)
    assert out_seq is not None
    # Frames of another data set against the map: off the map, every answer wrong.
    away = np.arange(nq, full.n_query)
    f_single = single_answers([all_results[i] for i in away], None, routes, profile)
    f_single.query = away
    f_seq = sequence_answers(all_results, full.gt, routes, params, [Drive.along(away)], profile)
    return (
        RoutePart(route.name, single, concat_answers([out_single, f_single])),
        RoutePart(route.name, drives, concat_answers([out_seq, f_seq])),
    )


def flips(accepted: np.ndarray) -> int:
    """Changes of ``accepted`` after its first True."""
    a = np.asarray(accepted, dtype=bool)
    first = np.flatnonzero(a)
    if not len(first):
        return 0
    return int(np.sum(a[first[0] + 1 :] != a[first[0] : -1]))


def evaluate(route: Route, policy: Policy, params: FilterParams) -> dict[str, Any]:
    """The policy on the route's test part (in the map, off it, and leaving and coming
    back)."""
    bank, config = route.test, route.config
    routes = RouteMap.from_metadata(bank.n_db)
    results = bank.results(config)
    profile = bank.profile(config)

    nq, nf = route.n_test, route.n_foreign
    inside = np.arange(nq)
    away = np.arange(nq, nq + nf)
    out: dict[str, Any] = {"gp": route.name.startswith("gp_")}
    single = single_answers([results[i] for i in inside], bank.gt[:nq], routes, profile)
    s = apply_acceptance(policy, single)
    out["single"] = _figures(s, single)
    seq = sequence_answers(results, bank.gt, routes, params, [Drive.along(inside)], profile)
    q = apply_acceptance(policy, seq, sequence=True)
    acc = np.array(q["accepted_answers"], bool)
    entry = apply_acceptance(replace(policy, sequence_stay_threshold=None), seq, sequence=True)
    out["sequence"] = {
        **_figures(q, seq),
        # the same without the stay threshold: what the entry threshold alone accepts
        "entry_only": {"accepted": entry["accepted"], "precision": entry["precision"]},
        "recall_at_1": float(seq.correct.mean()),
        "flips_per_100": 100.0 * flips(acc) / len(acc),
        "p_correct": q["p_correct"],
        "correct": seq.correct.tolist(),
    }
    f_single = single_answers([results[i] for i in away], None, routes, profile)
    fs = apply_acceptance(policy, f_single)
    f_seq = sequence_answers(results, bank.gt, routes, params, [Drive.along(away)], profile)
    fq = apply_acceptance(policy, f_seq, sequence=True)
    out["foreign"] = {
        "n": nf,
        "single_accepted": fs["accepted"],
        "single_mean_p": _mean_p(fs),
        "sequence_accepted": fq["accepted"],
        "sequence_mean_p": _mean_p(fq),
        "sequence_off_map": float(np.mean(fq["off_map"])),
    }
    a, b = AWAY
    frames = np.concatenate([inside[:a], away[:b], inside[a:]])
    trip = sequence_answers(results, bank.gt, routes, params, [Drive.along(frames)], profile)
    dec = decide(policy, trip, sequence=True)
    accepted = np.array([d.accepted for d in dec], bool)
    off = np.array([d.off_map for d in dec], bool)
    is_away = np.isin(frames, away)
    back = np.flatnonzero(accepted[a + b :])
    right = trip.correct
    out["leave_and_return"] = {
        "away_accepted": float(accepted[is_away].mean()),
        "away_said_off_map": float(off[is_away].mean()),
        "frames_to_accept_after_return": int(back[0]) + 1 if len(back) else None,
        "precision_in_map": (
            float(right[accepted & ~is_away].mean()) if (accepted & ~is_away).any() else None
        ),
        "accepted_in_map": float(accepted[~is_away].mean()),
    }
    return out


def evaluate_whole(route: Route, policy: Policy, params: FilterParams) -> dict[str, Any]:
    """The policy on the route's whole traverse: its map of every reference, its queries
    driven once in order. Unlike a test part (stretches of 20 frames joined into one map
    and one drive, where an estimate one reference behind across a join is 21 frames off),
    no place is next to one it is not next to on the route. Only the held-out fit is new to
    the route's frames; a Gardens Point traverse also appears in the other protocols'
    training parts, paired with another traverse."""
    bank = route.whole()
    routes = RouteMap.from_metadata(bank.n_db)
    results, profile = route.whole_results()
    single = single_answers(results, bank.gt, routes, profile)
    seq = sequence_answers(results, bank.gt, routes, params, None, profile)
    s = apply_acceptance(policy, single)
    q = apply_acceptance(policy, seq, sequence=True)
    acc = np.array(q["accepted_answers"], bool)
    return {
        "single": _figures(s, single),
        "sequence": {
            **_figures(q, seq),
            "recall_at_1": float(seq.correct.mean()),
            "flips_per_100": 100.0 * flips(acc) / len(acc),
            "wrong_accepted": np.flatnonzero(acc & ~seq.correct).tolist(),
        },
    }


def pooled_ece(runs: Any) -> dict[str, float]:
    """Sequence-mode ECE over the routes' test parts pooled: every route, and the Gardens
    Point routes only."""
    out = {}
    for label, keep in (("all", lambda r: True), ("gardens_point", lambda r: r["gp"])):
        p, c = [], []
        for r in runs:
            if keep(r):
                p += [np.nan if x is None else x for x in r["sequence"]["p_correct"]]
                c += r["sequence"]["correct"]
        pa = np.asarray(p, dtype=np.float64)
        ok = np.isfinite(pa)
        out[label] = expected_calibration_error(pa[ok], np.asarray(c, dtype=bool)[ok])
    return out


def _mean_p(rep: dict[str, Any]) -> float | None:
    p = [x for x in rep["p_correct"] if x is not None]
    return float(np.mean(p)) if p else None


def _figures(rep: dict[str, Any], answers: Answers) -> dict[str, Any]:
    return {
        "rule": rep["rule"],
        "n": len(answers),
        "accepted": rep["accepted"],
        "precision": rep["precision"],
        "ece": rep.get("ece"),
        "right": float(answers.correct.mean()),
    }


def fit(
    singles: list[RoutePart],
    seqs: list[RoutePart],
    features: tuple[tuple[str, ...], tuple[str, ...]] = (SINGLE_FEATURES, SEQUENCE_FEATURES),
    stay: float = STAY_P,
    gate: tuple[str, ...] = (),
    single_share: float = OFF_SHARE,
    stay_ref_z: float | None = None,
) -> tuple[Policy, dict[str, Any]]:
    """The pooled models of ``singles`` / ``seqs`` (on ``features``: single frame,
    sequence) and their thresholds, as a policy; ``stay``: the sequence stay threshold
    (hysteresis), at most the entry threshold, with its evidence floor ``stay_ref_z``
    (:attr:`Policy.sequence_stay_ref_z`); ``gate``: the models (``single``,
    ``sequence``) fitted with a gate (:meth:`ConfidenceModel.fit_gated`);
    ``single_share``: the single-frame model's share of off-map answers (the sequence
    model's is :data:`OFF_SHARE`)."""
    single_features, sequence_features = features
    model, thr, s_train = fit_pooled(
        singles, single_features, TARGET, outside_share=single_share, gate="single" in gate
    )
    smodel, sthr, q_train = fit_pooled(
        seqs, sequence_features, TARGET, outside_share=OFF_SHARE, gate="sequence" in gate
    )
    policy = Policy(
        model=model, model_threshold=thr, sequence_model=smodel, sequence_threshold=sthr
    )
    stay = min(stay, sthr)
    policy = replace(policy, sequence_stay_threshold=stay, sequence_stay_ref_z=stay_ref_z)
    q_train["as_decided"] = as_decided(seqs, policy, gate="sequence" in gate)
    return policy, {"single": s_train, "sequence": q_train, "stay_threshold": stay}


def _with_p(answers: Answers, p: np.ndarray) -> Answers:
    """``answers`` whose features are ``p``'s log-odds (for :data:`_IDENTITY`) and the
    answer's ``sequence_ref_z`` (what the stay rule's evidence floor reads)."""
    q = np.clip(np.asarray(p, dtype=np.float64), 1e-12, 1 - 1e-12)
    logit = np.log(q) - np.log1p(-q)
    return Answers(
        [
            {"p_logit": float(x), "sequence_ref_z": f.get("sequence_ref_z", float("nan"))}
            for x, f in zip(logit, answers.features, strict=True)
        ],
        answers.correct,
        answers.score,
        answers.query,
        answers.estimates,
        answers.drive,
    )


#: A model that returns its one feature's probability: decides given predictions through the
#: one policy (:func:`as_decided`).
_IDENTITY = ConfidenceModel(("p_logit",), (0.0,), (1.0,), (1.0,), 0.0)


def as_decided(seqs: list[RoutePart], policy: Policy, gate: bool = False) -> dict[str, Any]:
    """The sequence model's out-of-fold predictions on the training drives (five stretches
    of each route, as its threshold is chosen) decided as the service decides them
    (:func:`decide`: the stay threshold, the off-map state), and at the entry threshold
    alone (no stay). Per route: the in-map answers accepted and their precision, and the
    out-of-map ones accepted. The threshold is chosen frame by frame, without the stay;
    this says what it gives once the stay carries an accepted estimate on (``gate``: the
    sequence model is a gated one)."""
    assert policy.sequence_model is not None
    pred, _, g, inside = route_out_of_fold(
        seqs, policy.sequence_model.features, outside_share=OFF_SHARE, by="folds", gate=gate
    )
    rules = {
        "with_stay": replace(policy, sequence_model=_IDENTITY),
        "entry_only": replace(policy, sequence_model=_IDENTITY, sequence_stay_threshold=None),
    }
    out: dict[str, Any] = {}
    for k, part in enumerate(p for p in seqs if len(p.answers)):
        row: dict[str, Any] = {}
        for label, rule in rules.items():
            ans = _with_p(part.answers, pred[(g == k) & inside])
            acc = np.array([d.accepted for d in decide(rule, ans, sequence=True)], bool)
            fig = {
                "accepted": float(acc.mean()),
                "precision": float(ans.correct[acc].mean()) if acc.any() else None,
            }
            away = (g == k) & ~inside
            if part.outside is not None and away.any():
                o = _with_p(part.outside, pred[away])
                fig["outside_accepted"] = float(
                    np.mean([d.accepted for d in decide(rule, o, sequence=True)])
                )
            row[label] = fig
        out[part.name] = row
    return out


class Recipe(NamedTuple):
    """How the shipped models are fitted: each model's features, the sequence stay
    threshold (at most the entry threshold), the models fitted with a gate (``single``,
    ``sequence``), the single-frame model's share of off-map answers and the stay
    threshold's evidence floor (None: none). A recipe whose
    features include ``map_prior`` needs each route's prior (:func:`route_prior`)."""

    single: tuple[str, ...] = SINGLE_FEATURES
    sequence: tuple[str, ...] = SEQUENCE_FEATURES
    stay: float = STAY_P
    gate: tuple[str, ...] = ()
    single_share: float = OFF_SHARE
    stay_ref_z: float | None = None

    @property
    def features(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        return self.single, self.sequence

    @property
    def single_extra(self) -> tuple[str, ...]:
        """The single-frame model's features beyond :data:`SINGLE_FEATURES` and the prior."""
        return tuple(f for f in self.single if f not in SINGLE_FEATURES and f != "map_prior")

    @property
    def needs_prior(self) -> bool:
        return "map_prior" in self.single + self.sequence

    @classmethod
    def of(
        cls,
        map_prior: bool,
        stay: float = STAY_P,
        gate: Iterable[str] = (),
        single_share: float = OFF_SHARE,
        single_extra: Iterable[str] = (),
        stay_ref_z: float | None = None,
    ) -> Recipe:
        """The shipped features, with ``map_prior`` added to both models or not, and
        ``single_extra`` to the single-frame model's."""
        extra = ("map_prior",) if map_prior else ()
        single = SINGLE_FEATURES + tuple(single_extra) + extra
        return cls(single, SEQUENCE_FEATURES + extra, stay, tuple(gate), single_share, stay_ref_z)

    def describe(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "single": list(self.single),
            "sequence": list(self.sequence),
            "stay": self.stay,
        }
        if self.gate:
            out["gate"] = list(self.gate)
        if self.single_share != OFF_SHARE:
            out["single_share"] = self.single_share
        if self.stay_ref_z is not None:
            out["stay_ref_z"] = self.stay_ref_z
        return out


#: What made the models shipped before recipes were recorded.
DEFAULT_RECIPE = Recipe()


def shipped_recipe(preset: str) -> Recipe:
    """The recipe ``hmpf/presets/acceptance/<preset>.json`` was fitted with (its
    ``recipe``; a file without one: the default recipe, which made it)."""
    path = ROOT / "hmpf" / "presets" / "acceptance" / f"{preset}.json"
    doc = json.loads(path.read_text()) if path.is_file() else {}
    r = doc.get("recipe")
    if not r:
        return DEFAULT_RECIPE
    return Recipe(
        tuple(r["single"]),
        tuple(r["sequence"]),
        float(r["stay"]),
        tuple(r.get("gate", ())),
        float(r.get("single_share", OFF_SHARE)),
        None if r.get("stay_ref_z") is None else float(r["stay_ref_z"]),
    )


def route_priors(
    config: HierarchyConfig, names: Iterable[str], cache: FeatureCache, nordland_frames: int
) -> dict[str, dict[str, Any]]:
    """Each route's map prior (:func:`hmpf.evaluation.auto.map_prior`, computed once per
    reference traverse): the config's recall@1 on pseudo-queries of the route's references
    (the frames the route uses), as ``hmpf-index build --map-prior`` stores it for a map of
    those references; progress printed."""
    out: dict[str, dict[str, Any]] = {}
    by_folder: dict[str, dict[str, Any]] = {}
    for name in names:
        folder = ROUTES[name][0]
        if folder not in by_folder:
            paths = list_images(dataset_root() / folder)[: limit_of(name, nordland_frames)]
            by_folder[folder] = map_prior(config, paths, cache=cache)
            print(f"{folder}: pseudo-query recall@1 {by_folder[folder]['recall_at_1']:.3f}")
        out[name] = by_folder[folder]
    return out


def recipe_routes(
    config: HierarchyConfig,
    names: list[str],
    cache: FeatureCache,
    foreign: int,
    nordland_frames: int,
    recipe: Recipe,
) -> tuple[list[Route], dict[str, float | None]]:
    """The routes ``names``, each with its map prior when the recipe reads it (else None),
    and those priors by route."""
    entries = route_priors(config, names, cache, nordland_frames) if recipe.needs_prior else {}
    priors = {n: entries[n]["map_prior"] if entries else None for n in names}
    routes = [
        Route(n, config, cache, foreign, limit_of(n, nordland_frames), priors[n]) for n in names
    ]
    return routes, priors


def held_out(
    parts: list[tuple[RoutePart, RoutePart]], recipe: Recipe = DEFAULT_RECIPE
) -> list[tuple[Policy, dict[str, Any]]]:
    """Leave one route out: per route of ``parts`` (:func:`training_part`), the policy
    fitted (:func:`fit`, with ``recipe``) on the other routes' training parts only."""
    out = []
    for i in range(len(parts)):
        rest = [p for j, p in enumerate(parts) if j != i]
        out.append(fit_recipe(rest, recipe))
    return out


def fit_recipe(
    parts: Sequence[tuple[RoutePart, RoutePart]], recipe: Recipe
) -> tuple[Policy, dict[str, Any]]:
    """:func:`fit` of ``parts``' single-frame and sequence training answers, as ``recipe``
    says."""
    return fit(
        [p[0] for p in parts],
        [p[1] for p in parts],
        recipe.features,
        recipe.stay,
        recipe.gate,
        recipe.single_share,
        recipe.stay_ref_z,
    )


def out_of_the_box(preset: str) -> tuple[HierarchyConfig, HierarchyConfig, Policy]:
    """The bundled ``preset`` as a new user gets it: (the config with its shipped
    acceptance, the same without (to build the score banks), the policy the service runs
    on it: :meth:`Policy.of` of the shipped acceptance; quality / lock rules when the
    preset ships no model)."""
    shipped = load_config(preset)
    bare = shipped.model_copy(update={"acceptance": None})
    policy = Policy.of(shipped.acceptance, lock_mass=shipped.sequence_params().lock_mass)
    return shipped, bare, policy


def add_route_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every acceptance bench takes: the preset, the foreign frames per map and
    Nordland's subset."""
    ap.add_argument("--config", default="default", help="the bundled preset")
    ap.add_argument("--foreign", type=int, default=200, help="foreign frames per map")
    ap.add_argument(
        "--nordland-frames",
        type=int,
        default=NORDLAND_FRAMES,
        help="Nordland's first frames used (0: all 3576)",
    )
    if isinstance(ap, Parser):
        ap.smoke(foreign=20, nordland_frames=100)


class ModelSets(NamedTuple):
    """The three model sets the acceptance benches compare on the same routes."""

    shipped_config: HierarchyConfig  # the preset with its shipped acceptance
    config: HierarchyConfig  # the same without (the score banks are built with it)
    shipped: Policy  # the policy the service runs on the preset (:func:`out_of_the_box`)
    params: FilterParams  # the preset's sequence filter
    no_model: Policy  # the quality / lock rules (what a preset without a model decides)
    routes: list[Route]
    folds: list[tuple[Policy, dict[str, Any]]]  # per route: fitted on the others (held_out)


def model_sets(preset: str, names: Iterable[str], foreign: int, nordland_frames: int) -> ModelSets:
    """The banks of the routes ``names`` for ``preset`` and its three model sets: shipped,
    leave-one-route-out (:func:`held_out`) and none; progress printed."""
    t0 = time.perf_counter()
    shipped_config, config, shipped = out_of_the_box(preset)
    params = shipped_config.sequence_params()
    no_model = Policy.of(None, lock_mass=params.lock_mass)
    cache = FeatureCache(default_cache_dir())
    recipe = shipped_recipe(preset)
    routes = recipe_routes(config, list(names), cache, foreign, nordland_frames, recipe)[0]
    print(f"banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    folds = held_out([training_part(r, params) for r in routes], recipe)
    print(f"held-out folds fitted ({time.perf_counter() - t0:.0f} s)", flush=True)
    return ModelSets(shipped_config, config, shipped, params, no_model, routes, folds)


def report_head(
    args: argparse.Namespace,
    sets: ModelSets,
    note: str,
    goals: dict[str, Any],
    filter_key: str = "filter",
) -> dict[str, Any]:
    """What the acceptance benches' reports say first (after :func:`bench.harness.provenance`):
    the shipped models' file, the note, the target and goals, the sizes, the filter's settings
    and the shipped and no-model policies."""
    params = sets.params
    has_model = sets.shipped_config.acceptance is not None
    return {
        "shipped_models": f"hmpf/presets/acceptance/{args.config}.json" if has_model else None,
        "note": note,
        "target_precision": TARGET,
        "goals": goals,
        "foreign_frames": args.foreign,
        "nordland_frames": args.nordland_frames or "all",
        filter_key: {k: getattr(params, k) for k in params.__dataclass_fields__},
        "policies": {"shipped": sets.shipped.describe(), "no_model": sets.no_model.describe()},
    }


def route_policies(sets: ModelSets, i: int) -> dict[str, tuple[Policy, str]]:
    """Route ``sets.routes[i]``'s three policies, each with what its models are:
    ``shipped``, ``held_out`` (fitted on the other routes) and ``no_model``."""
    has_model = sets.shipped_config.acceptance is not None
    others = [r.name for j, r in enumerate(sets.routes) if j != i]
    return {
        "shipped": (sets.shipped, "shipped" if has_model else "none shipped (quality / lock)"),
        "held_out": (sets.folds[i][0], f"held out: fitted on {', '.join(others)}"),
        "no_model": (sets.no_model, "none (quality / lock rules)"),
    }


def held_out_fit(sets: ModelSets, i: int) -> dict[str, Any]:
    """Route ``i``'s held-out fit: its training figures and thresholds."""
    fold, train = sets.folds[i]
    return {"train": train, "thresholds": fold.describe()}


def settings_of(
    policy: Policy, note: str, map_prior_fallback: float | None = None
) -> AcceptanceSettings:
    assert policy.model is not None and policy.sequence_model is not None
    return AcceptanceSettings(
        threshold=policy.threshold,
        precision=TARGET,
        note=note,
        model=policy.model.to_dict(),
        model_threshold=policy.model_threshold,
        sequence_model=policy.sequence_model.to_dict(),
        sequence_threshold=policy.sequence_threshold,
        sequence_stay_threshold=policy.sequence_stay_threshold,
        map_prior_fallback=map_prior_fallback,
        sequence_stay_ref_z=policy.sequence_stay_ref_z,
    )


def goals(report: dict[str, Any]) -> list[str]:
    """The acceptance goals, judged on the held-out folds (Markdown lines)."""
    lines = [
        "| held-out route | single accepted (prec.) | sequence accepted (prec.) | seq. ECE | "
        "flips/100 | seq. recall@1 | foreign accepted single / seq. | foreign mean p | "
        "away accepted | back after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in report["folds"].items():
        s, q, f, t = r["single"], r["sequence"], r["foreign"], r["leave_and_return"]

        def pr(x: Any) -> str:
            return "n/a" if x is None else f"{x:.3f}"

        lines.append(
            f"| {name} | {s['accepted']:.3f} ({pr(s['precision'])}) | {q['accepted']:.3f} "
            f"({pr(q['precision'])}) | {pr(q['ece'])} | {q['flips_per_100']:.1f} | "
            f"{q['recall_at_1']:.3f} | {f['single_accepted']:.3f} / "
            f"{f['sequence_accepted']:.3f} | {pr(f['single_mean_p'])} / "
            f"{pr(f['sequence_mean_p'])} | {t['away_accepted']:.3f} | "
            f"{t['frames_to_accept_after_return']} |"
        )
    return lines


def fold_reports(
    routes: list[Route],
    parts: list[tuple[RoutePart, RoutePart]],
    params: FilterParams,
    t0: float,
    recipe: Recipe = DEFAULT_RECIPE,
) -> dict[str, Any]:
    """Per route: the policy fitted on the other routes (:func:`held_out`) on its test part
    and its whole traverse (:func:`evaluate_whole`)."""
    out = {}
    for route, (policy, train) in zip(routes, held_out(parts, recipe), strict=True):
        out[route.name] = {
            **evaluate(route, policy, params),
            "whole": evaluate_whole(route, policy, params),
            "train": train,
            "thresholds": policy.describe(),
        }
        print(f"fold {route.name} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return out


def shipped_report(
    routes: list[Route],
    parts: list[tuple[RoutePart, RoutePart]],
    params: FilterParams,
    recipe: Recipe = DEFAULT_RECIPE,
) -> tuple[Policy, dict[str, Any]]:
    """The shipped fit (every route's training part) and its figures on every test part
    and whole traverse."""
    policy, train = fit_recipe(parts, recipe)
    report: dict[str, Any] = {"train": train, "thresholds": policy.describe()}
    for route in routes:
        report[route.name] = {
            **evaluate(route, policy, params),
            "whole": evaluate_whole(route, policy, params),
        }
    return policy, report


def write_shipped(
    preset: str,
    config: HierarchyConfig,
    routes: list[Route],
    policy: Policy,
    recipe: Recipe = DEFAULT_RECIPE,
) -> Path:
    """``hmpf/presets/acceptance/<preset>.json``: the shipped fit, with the config's digest
    and the recipe it was fitted with. A recipe that reads the map's prior falls back, for a
    version that stores none, to the lowest prior of the routes fitted on (conservative)."""
    priors = [r.map_prior for r in routes if r.map_prior is not None]
    fallback = min(priors) if recipe.needs_prior and priors else None
    prior = (
        "; both models read the map's prior (map_prior: hmpf-index build --map-prior; "
        f"a version without one: {fallback:+.2f}, the lowest of these routes')"
        if fallback is not None
        else ""
    )
    floor = (
        ""
        if recipe.stay_ref_z is None
        else f" while the frame's sequence_ref_z is at least {recipe.stay_ref_z:g}"
    )
    note = (
        f"shipped with preset {preset!r}: fitted by bench/shipped_acceptance.py on "
        f"the training parts of {', '.join(r.name for r in routes)} (each route alike), "
        "thresholds for 99 % precision on out-of-fold predictions (stretches of each "
        f"route); sequence stay threshold {recipe.stay:g} (hysteresis){floor}{prior}"
    )
    doc = {
        "preset": preset,
        "digest": config.digest(),
        "routes": [r.name for r in routes],
        "recipe": recipe.describe(),
        # the filter the sequence model read: a config that leaves a setting unset gets it
        # with the models (hmpf.config.with_shipped_acceptance)
        "sequence": dict(config.sequence or {}),
        "acceptance": settings_of(policy, note, fallback).model_dump(exclude_none=True),
    }
    return write_json(ROOT / "hmpf" / "presets" / "acceptance" / f"{preset}.json", doc)


def with_filter(config: HierarchyConfig, settings: Sequence[str]) -> HierarchyConfig:
    """``config`` with the sequence filter settings ``NAME=VALUE`` over its own (a number:
    an integer setting's as int, else float; checked by :class:`FilterParams`)."""
    if not settings:
        return config
    seq = dict(config.sequence or {})
    for item in settings:
        name, sep, value = item.partition("=")
        if not sep or name not in FilterParams.__dataclass_fields__:
            raise SystemExit(f"--filter {item!r}: NAME=VALUE with a filter setting's name")
        kind = FilterParams.__dataclass_fields__[name].type
        try:
            seq[name] = int(value) if kind in ("int", int) else float(value)
        except ValueError:
            raise SystemExit(f"--filter {item!r}: not a number") from None
    FilterParams.from_mapping(seq)  # refused here, not after the banks are built
    return config.model_copy(update={"sequence": seq})


def gate_models(text: str) -> tuple[str, ...]:
    """``--gate``'s models: ``single``, ``sequence``, both, or none."""
    names = tuple(n.strip() for n in text.split(",") if n.strip() and n.strip() != "none")
    bad = [n for n in names if n not in ("single", "sequence")]
    if bad:
        raise SystemExit(f"--gate: unknown models {bad} (single, sequence, none)")
    return names


def stay_floor(text: str) -> float | None:
    """``--stay-ref-z``: a finite number, or ``none``."""
    if text.strip().lower() == "none":
        return None
    try:
        z = float(text)
    except ValueError:
        z = float("nan")
    if not np.isfinite(z):
        raise ValueError(f"--stay-ref-z must be a finite number or none, not {text!r}")
    return z


def single_extra(text: str) -> tuple[str, ...]:
    """``--single-extra``'s features: any a single-frame answer has, beyond the recipe's."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [
        n
        for n in names
        if n not in SINGLE_MODEL_FEATURES or n in SINGLE_FEATURES or n == "map_prior"
    ]
    if bad:
        raise SystemExit(f"--single-extra: not an extra single-frame feature: {bad}")
    return names


def main() -> int:
    ap = parser(__doc__)
    add_route_arguments(ap)
    ap.add_argument("--routes", default=",".join(ROUTES), help="comma-separated")
    ap.add_argument("--write", action="store_true", help="write the preset's shipped models")
    ap.add_argument(
        "--map-prior",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="both models read the map's prior (each route's, from pseudo-queries of its "
        "references, as hmpf-index build stores it); default: as the preset's shipped models",
    )
    ap.add_argument(
        "--stay",
        type=float,
        default=None,
        help=f"sequence stay threshold; default: the shipped models' (else {STAY_P})",
    )
    ap.add_argument(
        "--stay-ref-z",
        default=None,
        metavar="Z",
        help="the stay threshold's evidence floor (sequence_ref_z), or none; default: the "
        "shipped models'",
    )
    ap.add_argument(
        "--gate",
        default=None,
        metavar="MODELS",
        help="comma-separated models fitted with a gate, P(in map) x P(right | in map): "
        "single, sequence, or none; default: as the preset's shipped models",
    )
    ap.add_argument(
        "--single-share",
        type=float,
        default=None,
        help=f"the single-frame model's share of off-map answers (default: as the preset's "
        f"shipped models, else {OFF_SHARE})",
    )
    ap.add_argument(
        "--single-extra",
        default=None,
        metavar="FEATURES",
        help="comma-separated features added to the single-frame model's (e.g. ref_z_low); "
        "default: as the preset's shipped models",
    )
    ap.add_argument(
        "--filter",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="try a sequence filter setting over the preset's (repeatable; not with --write: "
        "the preset's own settings are what its shipped models are read with)",
    )
    add_json(ap, "--out", help="JSON report (default results/shipped_acceptance_<config>)")
    args = ap.parse_args()
    if args.filter and args.write:
        ap.error("--filter tries settings; change the preset's sequence: to ship them")
    if args.single_share is not None and not 0.0 <= args.single_share < 1.0:
        ap.error("--single-share must be in [0, 1)")
    t0 = time.perf_counter()
    config = with_filter(out_of_the_box(args.config)[1], args.filter)
    prov = provenance(args.config, config, args)
    params = config.sequence_params()
    cache = FeatureCache(default_cache_dir())
    # the shipped models' recipe unless told otherwise, so that --write refits them as they are
    shipped = shipped_recipe(args.config)
    floor = shipped.stay_ref_z
    if args.stay_ref_z is not None:
        try:
            floor = stay_floor(args.stay_ref_z)
        except ValueError as exc:
            ap.error(str(exc))
    recipe = Recipe.of(
        shipped.needs_prior if args.map_prior is None else args.map_prior,
        shipped.stay if args.stay is None else args.stay,
        shipped.gate if args.gate is None else gate_models(args.gate),
        shipped.single_share if args.single_share is None else args.single_share,
        shipped.single_extra if args.single_extra is None else single_extra(args.single_extra),
        floor,
    )
    routes, priors = recipe_routes(
        config, args.routes.split(","), cache, args.foreign, args.nordland_frames, recipe
    )
    print(f"banks ready ({time.perf_counter() - t0:.0f} s)", flush=True)
    parts = [training_part(r, params) for r in routes]
    report: dict[str, Any] = {
        "config": args.config,
        "target_precision": TARGET,
        "single_features": list(recipe.single),
        "sequence_features": list(recipe.sequence),
        "recipe": recipe.describe(),
        "map_priors": priors,
        "filter": {k: getattr(params, k) for k in params.__dataclass_fields__},
        "nordland_frames": args.nordland_frames or "all",
        "folds": fold_reports(routes, parts, params, t0, recipe),
    }
    policy, report["shipped"] = shipped_report(routes, parts, params, recipe)
    for key, runs in (
        ("folds", report["folds"]),
        ("shipped", {k: v for k, v in report["shipped"].items() if k in report["folds"]}),
    ):
        report[f"pooled_sequence_ece_{key}"] = pooled_ece(runs.values())
    report["wall_s"] = time.perf_counter() - t0
    out = write_record(
        args.out or ROOT / "results" / f"shipped_acceptance_{args.config}.json", report, prov=prov
    )
    print("\n".join(goals(report)))
    print(
        "pooled sequence ECE (test parts): held-out folds "
        f"{report['pooled_sequence_ece_folds']}, shipped {report['pooled_sequence_ece_shipped']}"
    )
    if args.write:
        print(f"wrote {write_shipped(args.config, config, routes, policy, recipe)}")
    print(f"wrote {out} ({report['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
