"""The calibrated acceptance of answers: fitting a config's confidence models, applying them.

``hmpf-calibrate`` fits, on the training part, a :class:`~hmpf.confidence.ConfidenceModel`
over a fixed feature set (:data:`SINGLE_FEATURES`; with ``--sequence`` also
:data:`SEQUENCE_MODEL_FEATURES` on the training drives) and the probability threshold for
the target precision (:func:`fit_acceptance`); ``hmpf-eval`` applies a config's models
(:func:`apply_acceptance`) and reports the figures at the config's thresholds
(:func:`acceptance_figures`).

*Why a fixed feature set.* ``bench/confidence.py`` chose features by greedy forward
selection on the four training parts pooled (route-balanced out-of-fold log-loss, in-map
answers only); with the absolute evidence among the candidates it chose ``tier1_margin``,
``agreement``, ``quality``, ``ref_z`` for single frames and ``sequence_logit``,
``sequence_ref_z``, ``tier1_rank`` for sequence mode (docs/experiments/confidence). One
route's training part (100 answers on Gardens Point) is too small to repeat that choice
reliably, so the calibrator uses those sets as they are.

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

from collections.abc import Sequence
from typing import Any

import numpy as np

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
from hmpf.sequence import FilterParams, RouteMap, SequenceFilter

__all__ = [
    "FOLDS",
    "L2",
    "OUTSIDE_SHARE",
    "SEQUENCE_MODEL_FEATURES",
    "SINGLE_FEATURES",
    "Answers",
    "acceptance_figures",
    "apply_acceptance",
    "fit_acceptance",
    "outside_answers",
    "outside_floor",
    "sequence_answers",
    "single_answers",
]

#: Single-frame model features (chosen by ``bench/confidence.py`` on the training parts).
SINGLE_FEATURES = ("tier1_margin", "agreement", "quality", "ref_z")
#: Sequence model features (idem).
SEQUENCE_MODEL_FEATURES = ("sequence_logit", "sequence_ref_z", "tier1_rank")
FOLDS = 5
L2 = 1.0
#: Weight of the out-of-map training answers, as a share of all (:func:`fit_acceptance`).
OUTSIDE_SHARE = 0.1


class Answers:
    """Answers of one part: per answer its features, whether it is right, today's score
    (Combined z, or the posterior mass in sequence mode) and its query index."""

    def __init__(
        self,
        features: list[dict[str, float]],
        correct: np.ndarray,
        score: np.ndarray,
        query: np.ndarray,
    ) -> None:
        self.features = features
        self.correct = np.asarray(correct, dtype=bool)
        self.score = np.asarray(score, dtype=np.float64)
        self.query = np.asarray(query, dtype=np.int64)

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
    filt = SequenceFilter(routes, params)
    evs = evidences_of(results, routes.n, params.proposals)
    feats, correct, mass, query = [], [], [], []
    for d in drives:
        run = drive(filt, evs, d, truth)
        for q, est, ok in zip(d.frames, run.estimates, run.correct, strict=True):
            feats.append(answer_features(results[int(q)], routes, estimate=est, profile=profile))
            correct.append(bool(ok))
            mass.append(est.mass)
            query.append(int(q))
    return Answers(feats, np.array(correct, bool), np.array(mass, float), np.array(query, int))


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
            seq.append(
                Answers(
                    [f for f, k in zip(run.features, pick, strict=True) if k],
                    np.zeros(int(pick.sum()), bool),
                    run.score[pick],
                    run.query[pick],
                )
            )
    return _concat(single), (_concat(seq) if params is not None else None)


def _concat(parts: Sequence[Answers]) -> Answers:
    return Answers(
        [f for a in parts for f in a.features],
        np.concatenate([a.correct for a in parts]) if parts else np.zeros(0, bool),
        np.concatenate([a.score for a in parts]) if parts else np.zeros(0),
        np.concatenate([a.query for a in parts]) if parts else np.zeros(0, np.int64),
    )


def outside_floor(p_outside: np.ndarray, max_rate: float) -> float:
    """The lowest threshold under which at most ``max_rate`` of the out-of-map answers
    (``p_outside``) are accepted (``p >= threshold``); none given: 0."""
    p = np.sort(np.asarray(p_outside, dtype=np.float64))[::-1]
    k = int(np.floor(max_rate * len(p) + 1e-9))  # answers that may be accepted
    if k >= len(p):
        return 0.0
    return float(np.nextafter(p[k], np.inf))


def fit_acceptance(
    answers: Answers,
    names: Sequence[str],
    target: float,
    outside: Answers | None = None,
    *,
    outside_share: float = OUTSIDE_SHARE,
) -> tuple[ConfidenceModel, float, dict[str, Any]]:
    """The model fitted on ``answers`` and its threshold for ``target`` precision, chosen on
    out-of-fold predictions; with the training figures at that threshold.

    With ``outside`` (answers to queries from places the map does not hold,
    :func:`outside_answers`): they join the fit as wrong answers weighing together
    ``outside_share`` of all answers (the model's ``p_correct`` is then for a stream of
    queries of which that share comes from outside the map), and the threshold must also
    keep the out-of-fold false accepts among them at or below ``1 - target``.

    Raises:
        ModelError: too few answers, or only right or only wrong ones (nothing to learn).
    """
    n_in = len(answers)
    X = feature_matrix(answers.features, names)
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
        X = np.vstack([X, feature_matrix(outside.features, names)])
        y = np.concatenate([y, np.zeros(n_out)])
        w = np.concatenate([w, np.full(n_out, outside_share / (1 - outside_share) * n_in / n_out)])
        query = np.concatenate([query, outside.query])
    else:
        n_out = 0
    model = ConfidenceModel.fit(X, y, names, l2=L2, sample_weight=w)
    groups = _folds(query)
    oof = np.empty(len(y))
    for g in np.unique(groups):
        hold = groups == g
        if y[~hold].min() == y[~hold].max():  # a fold's complement with one class
            oof[hold] = model.predict(X[hold])
            continue
        fold = ConfidenceModel.fit(X[~hold], y[~hold], names, l2=L2, sample_weight=w[~hold])
        oof[hold] = fold.predict(X[hold])
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


def apply_acceptance(
    acceptance: AcceptanceSettings | None,
    answers: Answers,
    *,
    sequence: bool = False,
    lock_mass: float | None = None,
) -> dict[str, Any]:
    """A config's acceptance applied to ``answers``.

    Returns ``rule`` ("model": ``p_correct >= model_threshold`` (or ``sequence_threshold``);
    "z": Combined quality >= ``threshold``; "mass" (sequence mode without a sequence model):
    posterior mass >= ``lock_mass``, the filter's lock threshold; "none": nothing to decide
    with), ``p_correct`` per answer (None without a model, never a made-up number),
    ``accepted_answers`` per answer (None under "none"), and the figures at the rule's threshold
    (:func:`acceptance_figures`; ECE only for the model).
    """
    model = None if acceptance is None else acceptance.confidence_model(sequence=sequence)
    if model is not None and acceptance is not None:
        threshold = acceptance.sequence_threshold if sequence else acceptance.model_threshold
        assert threshold is not None  # validated at load
        p = np.asarray(model.predict(feature_matrix(answers.features, model.features)))
        figs = acceptance_figures(p, answers.correct, threshold)
        return {
            "rule": "model",
            "p_correct": [float(x) for x in p],
            "accepted_answers": (p >= threshold).tolist(),
            **figs,
        }
    p_none: list[float | None] = [None] * len(answers)
    if sequence:
        rule, fallback = "mass", lock_mass
    else:
        rule, fallback = "z", None if acceptance is None else acceptance.threshold
    if fallback is None:
        return {"rule": "none", "p_correct": p_none, "accepted_answers": [None] * len(answers)}
    figs = acceptance_figures(answers.score, answers.correct, fallback, probability=False)
    acc = np.nan_to_num(answers.score, nan=-np.inf) >= fallback
    return {"rule": rule, "p_correct": p_none, "accepted_answers": acc.tolist(), **figs}
