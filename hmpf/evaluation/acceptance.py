"""The calibrated acceptance of answers: fitting a config's confidence models, applying them.

``hmpf-calibrate`` fits, on the training part, a :class:`~hmpf.confidence.ConfidenceModel`
over a fixed feature set (:data:`SINGLE_FEATURES`; with ``--sequence`` also
:data:`SEQUENCE_MODEL_FEATURES` on the training drives) and the probability threshold for
the target precision (:func:`fit_acceptance`); ``hmpf-eval`` applies a config's models
(:func:`apply_acceptance`) and reports the figures at the config's thresholds
(:func:`acceptance_figures`).

*Why a fixed feature set.* ``bench/confidence.py`` chose features by greedy forward
selection on the four training parts pooled (route-balanced out-of-fold log-loss); it chose
``tier1_margin``, ``agreement``, ``quality`` for single frames and ``sequence_logit``,
``sequence_agrees``, ``tier1_rank`` for sequence mode (docs/experiments/confidence). One
route's training part (100 answers on Gardens Point) is too small to repeat that choice
reliably, so the calibrator uses those sets as they are.

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
    answer_features,
    expected_calibration_error,
    feature_matrix,
    threshold_for_precision,
)
from hmpf.config import AcceptanceSettings
from hmpf.evaluation.sequence import Drive, drive, evidences_of
from hmpf.hierarchy import HierarchyResult
from hmpf.sequence import FilterParams, RouteMap, SequenceFilter

__all__ = [
    "FOLDS",
    "L2",
    "SEQUENCE_MODEL_FEATURES",
    "SINGLE_FEATURES",
    "Answers",
    "acceptance_figures",
    "apply_acceptance",
    "fit_acceptance",
    "sequence_answers",
    "single_answers",
]

#: Single-frame model features (chosen by ``bench/confidence.py`` on the training parts).
SINGLE_FEATURES = ("tier1_margin", "agreement", "quality")
#: Sequence model features (idem).
SEQUENCE_MODEL_FEATURES = ("sequence_logit", "sequence_agrees", "tier1_rank")
FOLDS = 5
L2 = 1.0


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
    results: Sequence[HierarchyResult], gt: np.ndarray | None, routes: RouteMap
) -> Answers:
    """Every single-frame answer (``gt`` None: no ground truth, all marked wrong)."""
    feats = [answer_features(r, routes) for r in results]
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
            feats.append(answer_features(results[int(q)], routes, estimate=est))
            correct.append(bool(ok))
            mass.append(est.mass)
            query.append(int(q))
    return Answers(feats, np.array(correct, bool), np.array(mass, float), np.array(query, int))


def _folds(query: np.ndarray) -> np.ndarray:
    nq = int(query.max()) + 1 if len(query) else 1
    return np.minimum(query * FOLDS // nq, FOLDS - 1)


def fit_acceptance(
    answers: Answers, names: Sequence[str], target: float
) -> tuple[ConfidenceModel, float, dict[str, Any]]:
    """The model fitted on ``answers`` and its threshold for ``target`` precision, chosen on
    out-of-fold predictions; with the training figures at that threshold.

    Raises:
        ModelError: too few answers, or only right or only wrong ones (nothing to learn).
    """
    X = feature_matrix(answers.features, names)
    y = answers.correct.astype(np.float64)
    if len(y) < 2 * FOLDS or y.min() == y.max():
        raise ModelError(
            f"cannot fit a confidence model on {len(y)} training answers "
            f"({int(y.sum())} right): too few, or all right or all wrong"
        )
    model = ConfidenceModel.fit(X, y, names, l2=L2)
    groups = _folds(answers.query)
    oof = np.empty(len(y))
    for g in np.unique(groups):
        hold = groups == g
        if y[~hold].min() == y[~hold].max():  # a fold's complement with one class
            oof[hold] = model.predict(X[hold])
            continue
        oof[hold] = ConfidenceModel.fit(X[~hold], y[~hold], names, l2=L2).predict(X[hold])
    threshold = threshold_for_precision(oof, answers.correct, target)
    train = acceptance_figures(np.asarray(model.predict(X)), answers.correct, threshold)
    train["out_of_fold"] = acceptance_figures(oof, answers.correct, threshold)
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
