"""bench/sequence.py's pure parts on synthetic drives: what it reports as accepted, off the
map and flipping is what the one policy decides (:func:`hmpf.evaluation.acceptance.decide`),
the hysteresis and the off-map state included."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.acceptance import Policy
from hmpf.confidence import ConfidenceModel
from hmpf.evaluation.acceptance import Answers, decide
from hmpf.evaluation.sequence import Drive
from hmpf.sequence import Estimate

ROOT = Path(__file__).resolve().parents[2]
SEQ = ("sequence_logit", "sequence_ref_z")


@pytest.fixture(scope="module")
def bench():
    path = ROOT / "bench" / "sequence.py"
    spec = importlib.util.spec_from_file_location("bench_sequence", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _answers(mass, correct, off=None, continuous=None, drive=None) -> Answers:
    n = len(mass)
    off = np.zeros(n) if off is None else np.asarray(off, float)
    cont = np.ones(n, bool) if continuous is None else np.asarray(continuous, bool)
    drive = np.zeros(n, int) if drive is None else np.asarray(drive, int)
    est = [
        Estimate(i, float(m), m >= 0.99, i + 1, 1.0, off_map=float(o), continuous=bool(c))
        for i, (m, o, c) in enumerate(zip(mass, off, cont, strict=True))
    ]
    feats = [{"sequence_logit": 4 * (m - 0.9), "sequence_ref_z": 1.0} for m in mass]
    return Answers(feats, np.asarray(correct, bool), np.asarray(mass), np.arange(n), est, drive)


def _decided(policy, answers):
    dec = decide(policy, answers, sequence=True)
    return np.array([d.accepted for d in dec]), np.array([d.off_map for d in dec])


def test_right_runs_and_their_flips_by_hand(bench):
    correct = [1] * 12 + [0] + [1] * 5 + [1] * 11
    cont = [True] * 29
    cont[18] = False  # the estimate jumps: a new stretch starts there
    drive = [0] * 23 + [1] * 6  # and a new drive at 23
    a = _answers(np.full(29, 0.995), correct, continuous=cont, drive=drive)
    assert bench.right_runs(a, min_len=5) == [(0, 12), (13, 18), (18, 23), (23, 29)]
    assert bench.right_runs(a, min_len=10) == [(0, 12)]
    acc = np.array([0, 1, 1, 0, 1] + [1] * 24, bool)
    assert bench.run_flips(acc, [(0, 5), (5, 10)]) == (3, 10)
    assert bench.run_flips(acc, []) == (0, 0)


def test_lock_rule_figures_are_the_policys_decisions(bench):
    # Mass between the unlock (0.9) and lock (0.99) bars after a lock: the hysteresis keeps
    # it; a bare threshold on the mass would flicker. Off-map frames are refused.
    mass = np.array([0.5, 0.995, 0.95, 0.95, 0.995, 0.95, 0.5, 0.95, 0.995, 0.995] * 3)
    correct = np.ones(len(mass), bool)
    correct[6] = correct[16] = False
    off = np.zeros(len(mass))
    off[20:23] = 0.8
    a = _answers(mass, correct, off=off)
    policy = Policy.of(None, lock_mass=0.99)
    acc, said = _decided(policy, a)
    fig = bench.policy_figures(policy, a, goal=0.5)
    assert fig["rule"] == "lock"
    assert fig["accepted"] == pytest.approx(acc.mean())
    assert fig["accepted"] != pytest.approx(np.mean(mass >= 0.99))  # the hysteresis counts
    assert fig["precision"] == pytest.approx(correct[acc].mean())
    assert fig["said_off_map"] == pytest.approx(said.mean()) and said.sum() == 3
    assert not acc[20:23].any()
    first = int(np.argmax(acc))
    assert fig["flips_per_100"] == pytest.approx(
        100 * np.sum(acc[first + 1 :] != acc[first:-1]) / len(acc)
    )
    runs = bench.right_runs(a)
    k = sum(int(np.sum(acc[s + 1 : e] != acc[s : e - 1])) for s, e in runs)
    assert fig["right_runs"]["flips"] == k
    assert fig["right_runs"]["frames"] == sum(e - s for s, e in runs)
    assert fig["goal_met"] == (correct[acc].mean() >= 0.99 and acc.mean() >= 0.5)


def test_model_rule_figures_and_first_accepts_are_the_policys(bench):
    rng = np.random.default_rng(0)
    n = 60
    mass = np.clip(rng.normal(0.9, 0.08, n), 0, 1)
    correct = mass + rng.normal(0, 0.03, n) > 0.88
    a = _answers(mass, correct, drive=np.repeat([0, 1, 2], 20))
    X = np.array([[f[k] for k in SEQ] for f in a.features])
    model = ConfidenceModel.fit(X, correct, SEQ)
    policy = Policy(sequence_model=model, sequence_threshold=0.8, sequence_stay_threshold=0.5)
    acc, _ = _decided(policy, a)
    assert 0 < acc.sum() < n
    fig = bench.policy_figures(policy, a)
    assert fig["rule"] == "p_correct" and "goal_met" not in fig
    assert fig["accepted"] == pytest.approx(acc.mean())
    assert fig["precision"] == pytest.approx(correct[acc].mean())
    drives = [Drive.along(np.arange(20)), Drive.along(np.arange(20), splice=5), Drive.along([0])]
    # a decision is carried within a drive only: the first of each drive starts unheld
    got = bench.first_accepts(policy, a, drives)
    want = []
    for i, d in enumerate(drives):
        hit = np.flatnonzero(acc[a.drive == i][d.splice or 0 :])
        want.append(int(hit[0]) + 1 if len(hit) else None)
    ok = [w for w in want if w is not None]
    assert got["never"] == sum(w is None for w in want)
    assert got["median"] == (pytest.approx(np.median(ok)) if ok else None)
