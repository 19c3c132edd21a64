"""bench/confidence.py's pure parts on synthetic answers: it reports the one policy's
``p_correct`` and decisions, and its calibration figures are the ones computed by hand."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.acceptance import Policy
from hmpf.confidence import ConfidenceModel, expected_calibration_error
from hmpf.evaluation.acceptance import SINGLE_FEATURES, Answers, decide
from hmpf.sequence import Estimate

ROOT = Path(__file__).resolve().parents[2]
SEQ = ("sequence_logit", "sequence_ref_z")


@pytest.fixture(scope="module")
def conf():
    path = ROOT / "bench" / "confidence.py"
    spec = importlib.util.spec_from_file_location("bench_confidence", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_auc_and_ece_floor_by_hand(conf):
    assert conf.auc(np.array([1.0, 2.0, 3.0, 4.0]), np.array([0, 0, 1, 1], bool)) == 1.0
    assert conf.auc(np.array([1.0, 2.0, 3.0]), np.array([1, 0, 1], bool)) == 0.5
    assert np.isnan(conf.auc(np.ones(3), np.ones(3, bool)))
    # Certain predictions cannot be miscalibrated by sampling.
    assert conf.ece_floor(np.array([0.0, 1.0, 1.0])) == 0.0
    assert 0.0 < conf.ece_floor(np.full(50, 0.5)) < 0.3


def test_calibration_skips_answers_without_a_probability(conf):
    p = [0.9, None, 0.2, 0.8]
    c = np.array([True, True, False, False])
    cal = conf.calibration(p, c)
    assert cal["n"] == 3 and cal["right"] == pytest.approx(1 / 3)
    assert cal["ece"] == pytest.approx(
        expected_calibration_error(np.array([0.9, 0.2, 0.8]), np.array([1, 0, 0], bool))
    )
    assert cal["mean_p"] == pytest.approx(1.9 / 3)
    assert conf.calibration([None, None], c[:2]) == {"n": 0, "ece": None}


def test_goals_are_issue_30s(conf):
    assert conf.meets("sequence", True, 0.85, 0.99) is True
    assert conf.meets("sequence", True, 0.84, 1.0) is False
    assert conf.meets("sequence", True, 0.9, 0.98) is False
    assert conf.meets("sequence", False, 0.5, 1.0) is True
    assert conf.meets("single", True, 0.3, 0.995) is True
    assert conf.meets("single", True, 0.3, None) is False
    assert conf.meets("single", False, 0.9, 1.0) is None


def _route(seed: int, n: int = 80):
    """A route's answers (:func:`bench.confidence.route_answers`' shape), a model pair
    fitted on them."""
    rng = np.random.default_rng(seed)

    def part(names, n, right, sequence):
        X = rng.normal(size=(n, len(names))) + (0.0 if right else -2.0)
        correct = (X[:, 0] + rng.normal(scale=0.5, size=n) > 0) if right else np.zeros(n, bool)
        feats = [dict(zip(names, row, strict=True)) for row in X]
        est = drive = None
        if sequence:
            est = [
                Estimate(i, 0.5, False, i + 1, 1.0, off_map=0.0, continuous=i > 0) for i in range(n)
            ]
            drive = np.zeros(n, int)
        return Answers(feats, correct, X[:, 0], np.arange(n), est, drive), X

    single, Xs = part(SINGLE_FEATURES, n, True, False)
    seq, Xq = part(SEQ, n, True, True)
    fs, _ = part(SINGLE_FEATURES, 30, False, False)
    fq, _ = part(SEQ, 30, False, True)
    answers = {"single": single, "sequence": seq, "foreign_single": fs, "foreign_sequence": fq}
    models = (
        ConfidenceModel.fit(Xs, single.correct, SINGLE_FEATURES),
        ConfidenceModel.fit(Xq, seq.correct, SEQ),
    )
    return answers, models


def test_measure_reports_the_policys_decisions_and_pooled_ece(conf):
    answers, (m1, m2) = _route(0)
    policy = Policy(
        model=m1,
        model_threshold=0.7,
        sequence_model=m2,
        sequence_threshold=0.8,
        sequence_stay_threshold=0.5,
    )
    out = conf.measure(policy, answers, gp=True)
    for mode, seq in (("single", False), ("sequence", True)):
        dec = decide(policy, answers[mode], sequence=seq)
        acc = np.array([d.accepted for d in dec])
        r = out[mode]
        assert r["rule"] == "p_correct"
        assert r["accepted"] == pytest.approx(acc.mean()) and acc.any()
        assert r["precision"] == pytest.approx(answers[mode].correct[acc].mean())
        p = np.array([d.p_correct for d in dec])
        assert r["calibration"]["ece"] == pytest.approx(
            expected_calibration_error(p, answers[mode].correct)
        )
        far = decide(policy, answers[f"foreign_{mode}"], sequence=seq)
        assert r["foreign"]["mean_p"] == pytest.approx(np.mean([d.p_correct for d in far]))
        assert set(r["feature_auc_test"]) == set(
            policy.sequence_model.features if seq else m1.features
        )
    # The hysteresis is the policy's: flips counted on its decisions.
    acc = np.array([d.accepted for d in decide(policy, answers["sequence"], sequence=True)])
    assert out["sequence"]["flips_per_100"] == pytest.approx(
        100 * np.sum(acc[np.argmax(acc) + 1 :] != acc[np.argmax(acc) : -1]) / len(acc)
    )
    none = conf.measure(Policy(threshold=0.0), answers, gp=True)
    assert none["single"]["rule"] == "quality" and none["sequence"]["rule"] == "lock"
    assert none["single"]["calibration"]["ece"] is None
    assert none["single"]["accepted"] == pytest.approx(np.mean(answers["single"].score >= 0))

    other, _ = _route(1)
    runs = {"gp_a": out, "nordland_s_w": conf.measure(policy, other, gp=False)}
    pooled = conf.pooled(runs, {"gp_a": answers, "nordland_s_w": other})
    p_all = np.array(out["sequence"]["_p"] + runs["nordland_s_w"]["sequence"]["_p"])
    c_all = np.concatenate([answers["sequence"].correct, other["sequence"].correct])
    assert pooled["sequence"]["all"]["ece"] == pytest.approx(
        expected_calibration_error(p_all, c_all)
    )
    assert pooled["sequence"]["gardens_point"]["n"] == len(answers["sequence"])
    assert pooled["sequence"]["gardens_point"]["ece"] == out["sequence"]["calibration"]["ece"]
