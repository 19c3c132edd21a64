"""The calibrated acceptance of answers: fitting a config's confidence models, applying them.

``hmpf-calibrate`` fits, on the training part, a :class:`~hmpf.confidence.ConfidenceModel`
over a fixed feature set (:data:`SINGLE_FEATURES`; with ``--sequence`` also
:data:`SEQUENCE_MODEL_FEATURES` on the training drives) and the probability threshold for
the target precision (:func:`fit_acceptance`); ``hmpf-eval`` applies a config's models
(:func:`apply_acceptance`) and reports the figures at the config's thresholds
(:func:`acceptance_figures`).

*Why a fixed feature set.* ``bench/confidence.py`` (in its earlier form, before it measured
the one policy out of the box) chose features by greedy forward selection on the four
training parts pooled (route-balanced out-of-fold log-loss, in-map answers only); with the
absolute evidence among the candidates it chose ``tier1_margin``, ``agreement``,
``quality``, ``ref_z`` for single frames and ``sequence_logit``, ``sequence_ref_z``,
``tier1_rank`` for sequence mode (docs/experiments/confidence). One route's training part
(100 answers on Gardens Point) is too small to repeat that choice reliably, so the
calibrator uses those sets as they are.

*Out-of-map answers.* Every other feature compares the map's references with each other, so
a query from a place the map does not hold can look like a right answer; ``ref_z`` says how
the query's score compares with what unrelated references score there. The training part
itself gives examples of such queries (:func:`outside_answers`): they join the fit and bound
the threshold (:func:`fit_acceptance`).

*Why an out-of-fold threshold.* The threshold is chosen on predictions of the training
answers by models fitted without them (5 folds of consecutive queries), so it does not
trust the model's in-sample fit (as ``bench/confidence.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from hmpf.acceptance import Decision, Policy
from hmpf.confidence import (
    ConfidenceModel,
    ModelError,
    ReferenceProfile,
    answer_features,
    expected_calibration_error,
    feature_matrix,
    threshold_for_precision,
)
from hmpf.config import AcceptanceSettings, HierarchyConfig
from hmpf.evaluation.sequence import Drive, drive, evidences_of
from hmpf.evaluation.study import ScoreBank
from hmpf.hierarchy import HierarchyResult
from hmpf.sequence import Estimate, FilterParams, RouteMap, SequenceFilter

__all__ = [
    "FOLDS",
    "L2",
    "OUTSIDE_SHARE",
    "SEQUENCE_MODEL_FEATURES",
    "SINGLE_FEATURES",
    "STAGED_FEATURES",
    "Answers",
    "acceptance_figures",
    "apply_acceptance",
    "carried_terms",
    "concat_answers",
    "decide",
    "fit_acceptance",
    "RoutePart",
    "fit_pooled",
    "outside_answers",
    "route_out_of_fold",
    "outside_floor",
    "sequence_answers",
    "single_answers",
]

#: Single-frame model features (chosen by the earlier ``bench/confidence.py`` on the
#: training parts).
SINGLE_FEATURES = ("tier1_margin", "agreement", "quality", "ref_z")
#: Sequence model features (idem).
SEQUENCE_MODEL_FEATURES = ("sequence_logit", "sequence_ref_z", "tier1_rank")
FOLDS = 5
L2 = 1.0
#: Weight of the out-of-map training answers, as a share of all (:func:`fit_acceptance`).
OUTSIDE_SHARE = 0.1
#: Features that enter a model as fixed log-odds offsets, not fitted
#: (:meth:`~hmpf.confidence.ConfidenceModel.fit`'s ``offsets``): ``map_prior``, the log-odds
#: of the map's pseudo-query recall (a per-map prior; ``bench/map_prior.py``).
OFFSET_FEATURES = frozenset({"map_prior"})
#: Features fitted in a second stage, on top of the model of the others
#: (:meth:`~hmpf.confidence.ConfidenceModel.fit_staged`): the hinges ``ref_z_low`` and
#: ``cand_z_low`` (a frame scoring below what unrelated places get, at the answer or at
#: every candidate) are 0 for most in-map answers, so they lower the probability of frames
#: from off the map and leave those answers' as they were.
STAGED_FEATURES = frozenset({"ref_z_low", "cand_z_low"})


def _fit(
    X: np.ndarray,
    y: np.ndarray,
    names: Sequence[str],
    w: np.ndarray,
    inside: np.ndarray | None = None,
) -> ConfidenceModel:
    """The models' one fit: L2 :data:`L2`, weights ``w``, :data:`OFFSET_FEATURES` as offsets,
    :data:`STAGED_FEATURES` in a second stage; with ``inside`` (which rows are in-map
    answers), a gated model (:meth:`ConfidenceModel.fit_gated`, every feature in one stage)
    where there are rows of both kinds."""
    offsets = [n for n in names if n in OFFSET_FEATURES]
    if inside is not None and inside.any() and not inside.all():
        return ConfidenceModel.fit_gated(
            X, y, names, inside, l2=L2, sample_weight=w, offsets=offsets
        )
    staged = [n for n in names if n in STAGED_FEATURES]
    return ConfidenceModel.fit_staged(X, y, names, staged, l2=L2, sample_weight=w, offsets=offsets)


class Answers:
    """Answers of one part: per answer its features, whether it is right, today's score
    (Combined z, or the posterior mass in sequence mode) and its query index; in sequence
    mode also each answer's :class:`~hmpf.sequence.Estimate` and the drive it belongs to
    (the policy's hysteresis carries a decision from one frame of a drive to the next)."""

    def __init__(
        self,
        features: list[dict[str, float]],
        correct: np.ndarray,
        score: np.ndarray,
        query: np.ndarray,
        estimates: list[Estimate] | None = None,
        drive: np.ndarray | None = None,
    ) -> None:
        self.features = features
        self.correct = np.asarray(correct, dtype=bool)
        self.score = np.asarray(score, dtype=np.float64)
        self.query = np.asarray(query, dtype=np.int64)
        self.estimates = estimates
        self.drive = None if drive is None else np.asarray(drive, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.features)


def single_answers(
    results: Sequence[HierarchyResult],
    gt: np.ndarray | None,
    routes: RouteMap,
    profile: ReferenceProfile | None = None,
) -> Answers:
    """Every single-frame answer (``gt`` None: no ground truth, all marked wrong)."""
    feats = [answer_features(r, routes, profile=profile) for r in results]
    if gt is None:
        correct = np.zeros(len(results), dtype=bool)
    else:
        correct = np.array([r.match >= 0 and bool(gt[q, r.match]) for q, r in enumerate(results)])
    quality = np.array([r.quality for r in results], dtype=np.float64)
    return Answers(feats, correct, quality, np.arange(len(results)))


def sequence_answers(
    results: Sequence[HierarchyResult],
    gt: np.ndarray | None,
    routes: RouteMap,
    params: FilterParams,
    drives: Sequence[Drive] | None = None,
    profile: ReferenceProfile | None = None,
) -> Answers:
    """Every answer of ``drives`` through the sequence filter (default: the queries once,
    in order), with its estimate's features; ``gt`` None: all marked wrong."""
    n_q = len(results)
    truth = np.zeros((n_q, routes.n), dtype=bool) if gt is None else np.asarray(gt, bool)
    drives = [Drive.along(np.arange(n_q))] if drives is None else drives
    evs = evidences_of(results, routes.n, params.proposals, profile)
    if profile is None:  # no absolute evidence: no off hypothesis (as sequence_report)
        params = params.with_(leave=0.0)
    filt = SequenceFilter(routes, params)
    feats, correct, mass, query = [], [], [], []
    estimates: list[Estimate] = []
    which: list[int] = []
    for i, d in enumerate(drives):
        run = drive(filt, evs, d, truth)
        for q, est, ok in zip(d.frames, run.estimates, run.correct, strict=True):
            feats.append(answer_features(results[int(q)], routes, estimate=est, profile=profile))
            correct.append(bool(ok))
            mass.append(est.mass)
            query.append(int(q))
            estimates.append(est)
            which.append(i)
    return Answers(
        feats,
        np.array(correct, bool),
        np.array(mass, float),
        np.array(query, int),
        estimates,
        np.array(which, int),
    )


def _folds(query: np.ndarray, nq: int | None = None) -> np.ndarray:
    """Fold of each answer: ``FOLDS`` stretches of consecutive queries of ``nq``."""
    if nq is None:
        nq = int(query.max()) + 1 if len(query) else 1
    return np.minimum(query * FOLDS // max(nq, 1), FOLDS - 1)


def outside_answers(
    bank: ScoreBank,
    config: HierarchyConfig,
    profile: ReferenceProfile | None = None,
    params: FilterParams | None = None,
) -> tuple[Answers, Answers | None]:
    """Answers to queries from places the map does not hold, made from the training part
    itself: for each of the :data:`FOLDS` stretches of consecutive queries, the references
    of that stretch (every one that is right for one of its queries) are removed from the
    map, and the stretch's queries with no right reference left are answered against the
    rest, every answer wrong by construction.

    Single frame: those answers. Sequence mode (``params`` given; else None): the whole
    part driven once, in order, through the filter over the reduced map, so the vehicle
    leaves the map and comes back; the frames of the removed stretch are kept.
    ``query`` is the query's index in the part, so the stretches are the folds of
    :func:`fit_acceptance`.
    """
    nq = bank.n_query
    groups = _folds(np.arange(nq), nq)
    single: list[Answers] = []
    seq: list[Answers] = []
    for g in range(FOLDS):
        qs = np.flatnonzero(groups == g)
        keep = np.flatnonzero(~bank.gt[qs].any(axis=0))
        if len(qs) == 0 or len(keep) < 2:
            continue
        sub = bank.subset(keep)
        out = qs[~sub.gt[qs].any(axis=1)]
        if len(out) == 0:
            continue
        routes = RouteMap.from_metadata(len(keep))
        prof = None if profile is None else profile.subset(keep)
        results = sub.results(config)
        feats = [answer_features(results[int(q)], routes, profile=prof) for q in out]
        score = np.array([results[int(q)].quality for q in out], dtype=np.float64)
        single.append(Answers(feats, np.zeros(len(out), bool), score, out))
        if params is not None:
            run = sequence_answers(results, sub.gt, routes, params, profile=prof)
            pick = np.isin(run.query, out)
            assert run.estimates is not None and run.drive is not None
            seq.append(
                Answers(
                    [f for f, k in zip(run.features, pick, strict=True) if k],
                    np.zeros(int(pick.sum()), bool),
                    run.score[pick],
                    run.query[pick],
                    [e for e, k in zip(run.estimates, pick, strict=True) if k],
                    run.drive[pick] + g * 1_000_000,
                )
            )
    return concat_answers(single), (concat_answers(seq) if params is not None else None)


def concat_answers(parts: Sequence[Answers]) -> Answers:
    """The answers of ``parts`` one after the other."""
    seq = bool(parts) and all(a.estimates is not None and a.drive is not None for a in parts)
    return Answers(
        [f for a in parts for f in a.features],
        np.concatenate([a.correct for a in parts]) if parts else np.zeros(0, bool),
        np.concatenate([a.score for a in parts]) if parts else np.zeros(0),
        np.concatenate([a.query for a in parts]) if parts else np.zeros(0, np.int64),
        [e for a in parts for e in (a.estimates or [])] if seq else None,
        np.concatenate([a.drive for a in parts if a.drive is not None]) if seq else None,
    )


def outside_floor(p_outside: np.ndarray, max_rate: float) -> float:
    """The lowest threshold under which at most ``max_rate`` of the out-of-map answers
    (``p_outside``) are accepted (``p >= threshold``); none given: 0."""
    p = np.sort(np.asarray(p_outside, dtype=np.float64))[::-1]
    k = int(np.floor(max_rate * len(p) + 1e-9))  # answers that may be accepted
    if k >= len(p):
        return 0.0
    return float(np.nextafter(p[k], np.inf))


def carried_terms(acceptance: AcceptanceSettings | None) -> dict[str, float]:
    """The staged terms (:data:`STAGED_FEATURES`) of ``acceptance``'s single-frame model with
    their coefficients: what a route's own fit carries over (:func:`fit_acceptance`'s
    ``carried``). Empty without a model, for a gated one, or where a staged feature was
    fitted with the others (not raw: mean 0, scale 1).

    Why carry them: the shipped model's hinges ``ref_z_low`` and ``cand_z_low`` were fitted
    on frames of other data sets (bench/shipped_acceptance.py, bench/offmap_hinge.py); a
    route's own training part has none (its out-of-map answers are the same route's
    neighbouring places, which score like the map), so a hinge fitted there learns next to
    nothing (measured: docs/calibration.md)."""
    if acceptance is None or acceptance.model is None:
        return {}
    model = ConfidenceModel.from_dict(acceptance.model)
    if model.gate is not None:
        return {}
    return {
        n: c
        for n, m, sc, c in zip(model.features, model.mean, model.scale, model.coef, strict=True)
        if n in STAGED_FEATURES and m == 0.0 and sc == 1.0
    }


def fit_acceptance(
    answers: Answers,
    names: Sequence[str],
    target: float,
    outside: Answers | None = None,
    *,
    outside_share: float = OUTSIDE_SHARE,
    gate: bool = False,
    carried: Mapping[str, float] | None = None,
) -> tuple[ConfidenceModel, float, dict[str, Any]]:
    """The model fitted on ``answers`` and its threshold for ``target`` precision, chosen on
    out-of-fold predictions; with the training figures at that threshold. ``gate``: a gated
    model (:meth:`ConfidenceModel.fit_gated`) where there are ``outside`` answers.
    ``carried``: raw terms with fixed coefficients (:func:`carried_terms`) added to every
    fit (:meth:`ConfidenceModel.with_terms`), the out-of-fold ones too, so the threshold is
    chosen on the model as it will predict.

    With ``outside`` (answers to queries from places the map does not hold,
    :func:`outside_answers`): they join the fit as wrong answers weighing together
    ``outside_share`` of all answers (the model's ``p_correct`` is then for a stream of
    queries of which that share comes from outside the map), and the threshold must also
    keep the out-of-fold false accepts among them at or below ``1 - target``.

    Raises:
        ModelError: too few answers, or only right or only wrong ones (nothing to learn).
    """
    n_in = len(answers)
    extra = dict(carried or {})
    if set(extra) & set(names):
        raise ModelError(f"carried terms {sorted(set(extra) & set(names))} are fitted features")
    if extra and gate:
        raise ModelError("carried terms cannot be added to a gated model")
    cols = (*names, *extra)
    X = feature_matrix(answers.features, cols)
    y = answers.correct.astype(np.float64)
    if n_in < 2 * FOLDS or y.min() == y.max():
        raise ModelError(
            f"cannot fit a confidence model on {len(y)} training answers "
            f"({int(y.sum())} right): too few, or all right or all wrong"
        )
    if not 0.0 <= outside_share < 1.0:
        raise ModelError("outside_share must be in [0, 1)")
    w = np.ones(n_in)
    query = answers.query
    n_out = 0 if outside is None else len(outside)
    if outside is not None and n_out and outside_share > 0:
        X = np.vstack([X, feature_matrix(outside.features, cols)])
        y = np.concatenate([y, np.zeros(n_out)])
        w = np.concatenate([w, np.full(n_out, outside_share / (1 - outside_share) * n_in / n_out)])
        query = np.concatenate([query, outside.query])
    else:
        n_out = 0
    inside = np.arange(len(y)) < n_in if gate else None
    fitted = len(names)

    def fit_rows(rows: np.ndarray) -> ConfidenceModel:
        m = _fit(
            X[rows, :fitted], y[rows], names, w[rows], None if inside is None else inside[rows]
        )
        return m.with_terms(extra) if extra else m

    model = fit_rows(np.ones(len(y), bool))
    groups = _folds(query)
    oof = np.empty(len(y))
    for g in np.unique(groups):
        hold = groups == g
        if y[~hold].min() == y[~hold].max():  # a fold's complement with one class
            oof[hold] = model.predict(X[hold])
            continue
        oof[hold] = fit_rows(~hold).predict(X[hold])
    floor = outside_floor(oof[n_in:], 1.0 - target) if n_out else 0.0
    threshold = threshold_for_precision(oof[:n_in], answers.correct, target, floor=floor)
    p_all = np.asarray(model.predict(X))
    train = acceptance_figures(p_all[:n_in], answers.correct, threshold)
    train["out_of_fold"] = acceptance_figures(oof[:n_in], answers.correct, threshold)
    if n_out:
        train["outside"] = {
            "n": n_out,
            "share": outside_share,
            "floor": floor,
            "accepted": float(np.mean(p_all[n_in:] >= threshold)),
            "accepted_out_of_fold": float(np.mean(oof[n_in:] >= threshold)),
        }
    return model, threshold, train


def acceptance_figures(
    score: np.ndarray, correct: np.ndarray, threshold: float, *, probability: bool = True
) -> dict[str, Any]:
    """Accepted share, precision (None when nothing is accepted) and, for probabilities,
    the expected calibration error, at ``score >= threshold``."""
    s = np.nan_to_num(np.asarray(score, dtype=np.float64), nan=-np.inf)
    c = np.asarray(correct, dtype=bool)
    acc = s >= threshold
    n = int(acc.sum())
    out: dict[str, Any] = {
        "threshold": float(threshold),
        "accepted": float(acc.mean()) if len(acc) else 0.0,
        "precision": float(c[acc].mean()) if n else None,
        "n_accepted": n,
        "n": int(len(c)),
    }
    if probability:
        out["ece"] = expected_calibration_error(s, c) if len(c) else None
    return out


def decide(policy: Policy, answers: Answers, *, sequence: bool = False) -> list[Decision]:
    """The policy's decision on every answer (:mod:`hmpf.acceptance`, what the service runs).

    Sequence mode needs the answers' estimates (:func:`sequence_answers`); within a drive, a
    frame is *held* when the previous frame's estimate was accepted or kept
    (:attr:`~hmpf.acceptance.Decision.holds`; the service carries the same bit in the
    vehicle's track)."""
    if not sequence:
        return [
            policy.single_from(f, q) for f, q in zip(answers.features, answers.score, strict=True)
        ]
    if answers.estimates is None or answers.drive is None:
        raise ModelError("sequence decisions need the answers' estimates (sequence_answers)")
    out: list[Decision] = []
    prev_drive, held = None, False
    for f, est, d in zip(answers.features, answers.estimates, answers.drive, strict=True):
        if d != prev_drive:
            prev_drive, held = d, False
        dec = policy.sequence_from(f, est, held=held)
        out.append(dec)
        held = dec.holds
    return out


def apply_acceptance(
    acceptance: AcceptanceSettings | Policy | None,
    answers: Answers,
    *,
    sequence: bool = False,
    lock_mass: float | None = None,
) -> dict[str, Any]:
    """A config's acceptance (or a :class:`~hmpf.acceptance.Policy`) applied to ``answers``
    through the one policy (:func:`decide`).

    Returns ``rule`` (``p_correct``, ``quality`` or ``lock``, as the service's
    ``accepted_by``), ``p_correct`` per answer (None without a model, never a made-up
    number), ``accepted_answers`` and ``off_map`` per answer, and the figures at the rule's
    threshold (:func:`acceptance_figures`; ECE only for a model).
    """
    policy = (
        acceptance
        if isinstance(acceptance, Policy)
        else Policy.of(acceptance, lock_mass=0.99 if lock_mass is None else lock_mass)
    )
    decisions = decide(policy, answers, sequence=sequence)
    rule = policy.sequence_rule if sequence else policy.single_rule
    accepted = np.array([d.accepted for d in decisions], dtype=bool)
    p = [d.p_correct for d in decisions]
    if rule == "p_correct":
        threshold = policy.sequence_threshold if sequence else policy.model_threshold
        probs = np.array([np.nan if x is None else x for x in p], dtype=np.float64)
        figs = acceptance_figures(probs, answers.correct, float(threshold or 0.0))
    else:
        threshold = policy.lock_mass if sequence else policy.threshold
        figs = acceptance_figures(answers.score, answers.correct, threshold, probability=False)
    # The decisions, not the bare threshold, say what was accepted (hysteresis, off map).
    n = int(accepted.sum())
    figs["accepted"] = float(accepted.mean()) if len(accepted) else 0.0
    figs["n_accepted"] = n
    figs["precision"] = float(answers.correct[accepted].mean()) if n else None
    return {
        "rule": rule,
        "p_correct": p,
        "accepted_answers": accepted.tolist(),
        "off_map": [d.off_map for d in decisions],
        **figs,
    }


# -- one model for many routes: the models the bundled presets ship ------------------------------


class RoutePart:
    """One route's training answers for a pooled fit: the in-map answers and the answers to
    queries from places the map does not hold (:func:`outside_answers`)."""

    def __init__(self, name: str, answers: Answers, outside: Answers | None = None) -> None:
        self.name = name
        self.answers = answers
        self.outside = outside


def _pooled(
    parts: Sequence[RoutePart], names: Sequence[str], outside_share: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(X, y, weight, route of each row, whether a row is an in-map answer) of ``parts``:
    each route's in-map answers weigh alike in total (routes of different lengths count
    alike), the mean route's answer 1 (so the regularisation weighs as in a one-route fit),
    and its out-of-map answers ``outside_share`` of the route's total."""
    sizes = [len(p.answers) for p in parts if len(p.answers)]
    per_route = float(np.mean(sizes)) if sizes else 0.0
    xs, ys, ws, gs, ins = [], [], [], [], []
    for g, part in enumerate(parts):
        n = len(part.answers)
        if n == 0:
            continue
        xs.append(feature_matrix(part.answers.features, names))
        ys.append(part.answers.correct.astype(np.float64))
        ws.append(np.full(n, per_route / n))
        gs.append(np.full(n, g))
        ins.append(np.ones(n, bool))
        m = 0 if part.outside is None else len(part.outside)
        if m and outside_share > 0:
            assert part.outside is not None
            xs.append(feature_matrix(part.outside.features, names))
            ys.append(np.zeros(m))
            ws.append(np.full(m, per_route * outside_share / (1 - outside_share) / m))
            gs.append(np.full(m, g))
            ins.append(np.zeros(m, bool))
    if not xs:
        raise ModelError("no training answers")
    return (
        np.vstack(xs),
        np.concatenate(ys),
        np.concatenate(ws),
        np.concatenate(gs),
        np.concatenate(ins),
    )


def route_out_of_fold(
    parts: Sequence[RoutePart],
    names: Sequence[str],
    *,
    outside_share: float = OUTSIDE_SHARE,
    by: str = "routes",
    gate: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Out-of-fold predictions of every training answer. ``by="routes"``: each route's
    answers predicted by the model fitted on the other routes (leave one route out);
    ``"folds"``: each of :data:`FOLDS` stretches of consecutive queries of each route by
    the model fitted on everything else (as :func:`fit_acceptance`, pooled). Returns (p, y,
    route, in-map)."""
    X, y, w, g, inside = _pooled(parts, names, outside_share)
    if by == "routes":
        groups = g
    elif by == "folds":
        folds = []
        for p in parts:
            if not len(p.answers):
                continue
            nq = int(p.answers.query.max()) + 1
            folds.append(_folds(p.answers.query, nq))
            if p.outside is not None and len(p.outside) and outside_share > 0:
                folds.append(_folds(np.minimum(p.outside.query, nq - 1), nq))
        groups = g * FOLDS + np.concatenate(folds)
    else:
        raise ModelError(f"unknown out-of-fold scheme {by!r}")
    oof = np.empty(len(y))
    for r in np.unique(groups):
        hold = groups == r
        if y[~hold].min() == y[~hold].max():
            raise ModelError("a fold's other routes hold only right or only wrong answers")
        model = _fit(X[~hold], y[~hold], names, w[~hold], inside[~hold] if gate else None)
        oof[hold] = model.predict(X[hold])
    return oof, y, g, inside


def fit_pooled(
    parts: Sequence[RoutePart],
    names: Sequence[str],
    target: float,
    *,
    outside_share: float = OUTSIDE_SHARE,
    outside_floor_rate: float | None = None,
    oof: str = "folds",
    gate: bool = False,
) -> tuple[ConfidenceModel, float, dict[str, Any]]:
    """One model over several routes' training answers (each route weighing alike), its
    threshold for ``target`` precision chosen on out-of-fold predictions (``oof``, see
    :func:`route_out_of_fold`: stretches of each route, or leave one route out), and, with
    ``outside_floor_rate``, bounded so that at most that share of the out-of-map
    answers are accepted; with the training figures at that threshold. ``gate``: a gated
    model (:meth:`~hmpf.confidence.ConfidenceModel.fit_gated`), the out-of-map answers
    teaching its gate."""
    if len(parts) < 2:
        raise ModelError("a pooled fit needs at least two routes")
    X, y, w, _, inside = _pooled(parts, names, outside_share)
    if y.min() == y.max():
        raise ModelError("the training answers are all right or all wrong")
    model = _fit(X, y, names, w, inside if gate else None)
    pred, _, _, _ = route_out_of_fold(parts, names, outside_share=outside_share, by=oof, gate=gate)
    bound = (~inside).any() and outside_floor_rate is not None
    floor = outside_floor(pred[~inside], float(outside_floor_rate or 0.0)) if bound else 0.0
    threshold = threshold_for_precision(pred[inside], y[inside].astype(bool), target, floor=floor)
    p_all = np.asarray(model.predict(X))
    train = acceptance_figures(p_all[inside], y[inside].astype(bool), threshold)
    train["out_of_fold"] = acceptance_figures(pred[inside], y[inside].astype(bool), threshold)
    train["out_of_fold"]["by"] = oof
    train["routes"] = [p.name for p in parts]
    if (~inside).any():
        train["outside"] = {
            "n": int((~inside).sum()),
            "share": outside_share,
            "floor": floor,
            "accepted": float(np.mean(p_all[~inside] >= threshold)),
            "accepted_out_of_fold": float(np.mean(pred[~inside] >= threshold)),
        }
    return model, threshold, train
