"""bench/out_of_map.py's pure parts on synthetic data."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.datasets import frame_ground_truth

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def oom():
    path = ROOT / "bench" / "out_of_map.py"
    spec = importlib.util.spec_from_file_location("bench_out_of_map", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_spread_picks_evenly_and_all_when_few(oom):
    assert oom.spread(10, 20).tolist() == list(range(10))
    idx = oom.spread(3576, 200)
    assert len(idx) == 200 and idx[0] == 0 and idx[-1] == 3575
    assert np.all(np.diff(idx) >= 17)
    assert oom.spread(10, 0).tolist() == []


def test_block_parts_match_the_calibrators_split(oom):
    from hmpf.evaluation.evaluate import EvalData
    from hmpf.evaluation.study import split_data

    paths = [Path(f"/x/{i:03d}.png") for i in range(100)]
    data = EvalData(paths, paths, frame_ground_truth(100, 100, 2), "frames +-2")
    train, test = split_data(data, block=20)
    tr, te = oom.block_parts(100, 20)
    assert [paths[i] for i in tr] == train.reference and [paths[i] for i in te] == test.query


def test_out_of_map_leaves_out_queries_next_to_a_join(oom):
    gt = frame_ground_truth(100, 100, 2)
    tr, te = oom.block_parts(100, 20)
    outside = oom.out_of_map(gt, te, tr)
    # Test stretches 20-39, 60-79: frames 20, 21 reach references 18, 19 (training), 38, 39
    # reach 40, 41; the 16 frames in between are out of the map.
    inside = te[~outside].tolist()
    assert inside == [20, 21, 38, 39, 60, 61, 78, 79]
    assert outside.sum() == len(te) - 8


def test_false_accepts_counts_only_out_of_map_queries(oom):
    accepted = np.array([True, True, False, False, True])
    outside = np.array([True, False, True, True, True])
    r = oom.false_accepts(accepted, outside)
    assert (r["n"], r["false_accepts"]) == (4, 2) and r["rate"] == 0.5 and r["met"] is False
    none = oom.false_accepts(np.zeros(300, bool), np.ones(300, bool))
    assert none["rate"] == 0 and none["met"] is True
    # Zero of 300: the rate can still be up to ~1 % (rule of three).
    assert none["upper_95"] == pytest.approx(1 - 0.05 ** (1 / 300), rel=1e-6)
    empty = oom.false_accepts(np.zeros(2, bool), np.zeros(2, bool))
    assert empty["rate"] is None and empty["met"] is None
    with pytest.raises(ValueError):
        oom.false_accepts(np.zeros(2, bool), np.zeros(3, bool))


def _answers(names, n=60, seed=0, sequence=False):
    from hmpf.evaluation.acceptance import Answers
    from hmpf.sequence import Estimate

    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, len(names)))
    feats = [dict(zip(names, row, strict=True)) for row in X]
    est = None
    if sequence:
        # A drive: the mass follows the first feature; the second half off the map.
        est = [
            Estimate(i, float(1 / (1 + np.exp(-3 * x))), False, i + 1, 1.0,
                     off_map=0.9 if i >= n // 2 else 0.0, continuous=i > 0)
            for i, x in enumerate(X[:, 0])
        ]  # fmt: skip
    drive = np.zeros(n, int) if sequence else None
    return Answers(feats, X[:, 0] > 0, X[:, 0], np.arange(n), est, drive), X


def test_off_map_rows_count_the_policys_decisions(oom):
    """The bench reports what the one policy decides, rule names included: a fitted model
    (p_correct), the quality rule, and in sequence mode the lock with the off-map state."""
    from hmpf.acceptance import Policy
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SINGLE_FEATURES, apply_acceptance, decide

    single, X = _answers(SINGLE_FEATURES)
    model = ConfidenceModel.fit(X, single.correct, SINGLE_FEATURES)
    policy = Policy(model=model, model_threshold=0.8)
    outside = np.arange(len(single)) % 3 != 0
    row = oom.off_map_rows(apply_acceptance(policy, single), outside)
    p = model.predict(X)
    assert row["rule"] == "p_correct"
    assert row["false_accepts"] == int(((p >= 0.8) & outside).sum()) > 0
    assert row["n"] == int(outside.sum())
    assert row["mean_p"] == pytest.approx(p[outside].mean())
    assert row["mean_p_met"] is False  # 0.39 > 0.1
    assert row["said_off_map"] == 0.0

    quality = oom.off_map_rows(apply_acceptance(Policy(threshold=0.5), single), outside)
    assert quality["rule"] == "quality" and quality["mean_p"] is None
    assert quality["false_accepts"] == int(((X[:, 0] >= 0.5) & outside).sum())

    seq, Xq = _answers(("sequence_logit",), sequence=True)
    lock = Policy(lock_mass=0.9, unlock_mass=0.5)
    rep = apply_acceptance(lock, seq, sequence=True)
    every = np.ones(len(seq), bool)
    row = oom.off_map_rows(rep, every)
    dec = decide(lock, seq, sequence=True)
    assert row["rule"] == "lock"
    assert row["false_accepts"] == sum(d.accepted for d in dec) > 0
    # Off the map (the second half): never accepted, and said so.
    assert not any(d.accepted for d in dec[len(dec) // 2 :])
    assert row["said_off_map"] == pytest.approx(0.5)


def test_tables_render_every_row(oom):
    rows = [
        {
            "map": "m", "models": "shipped", "queries": q, "mode": "single", "rule": "p_correct",
            **oom.false_accepts(np.array([True, False]), np.array([True, True])),
            "mean_p": 0.2, "mean_p_met": False, "said_off_map": None,
        }
        for q in ("foreign", "removed")
    ]  # fmt: skip
    text = oom.table(rows)
    assert text.count("\n") == 3
    assert "| m | shipped | foreign (2) | single | p_correct | 1 | 0.500 (" in text
    assert text.rstrip().endswith("| no / no |")
    in_map = [
        {"map": "m", "n": 100, "models": "held out", "mode": "sequence", "rule": "p_correct",
         "accepted": 0.9, "precision": 1.0, "ece": 0.04, "flips_per_100": 1.0,
         "recall_at_1": 0.97, "leave_and_return": "0.000, 3"}
    ]  # fmt: skip
    line = oom.in_map_table(in_map).splitlines()[-1]
    assert line == (
        "| m (100) | held out | sequence | p_correct | 0.900 | 1.000 | 0.040 | 1.0 | 0.970 "
        "| 0.000, 3 |"
    )
