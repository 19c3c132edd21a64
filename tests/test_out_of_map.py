"""bench/out_of_map.py's pure parts on synthetic data."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.datasets import frame_ground_truth

ROOT = Path(__file__).resolve().parent.parent


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
    with pytest.raises(ValueError):
        oom.spread(10, 0)


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


def test_decisions_and_table_on_a_synthetic_model(oom):
    from hmpf.confidence import ConfidenceModel
    from hmpf.evaluation.acceptance import SEQUENCE_MODEL_FEATURES, SINGLE_FEATURES, Answers

    rng = np.random.default_rng(0)

    def answers(names, n=50):
        X = rng.normal(size=(n, len(names)))
        feats = [dict(zip(names, row, strict=True)) for row in X]
        return Answers(feats, X[:, 0] > 0, X[:, 0], np.arange(n)), X

    single, Xs = answers(SINGLE_FEATURES)
    seq, Xq = answers(SEQUENCE_MODEL_FEATURES)
    m1 = ConfidenceModel.fit(Xs, single.correct, SINGLE_FEATURES)
    m2 = ConfidenceModel.fit(Xq, seq.correct, SEQUENCE_MODEL_FEATURES)
    fitted = {
        "variants": {
            "absolute": {
                "model": m1,
                "threshold": 0.8,
                "sequence_model": m2,
                "sequence_threshold": 0.9,
            }
        },
        "z": 0.5,
        "mass": 1.0,
    }
    out = oom.decisions(fitted, single, seq)
    assert [(m, r) for m, r, _, _ in out] == [
        ("sequence", "model (absolute)"),
        ("sequence", "mass"),
        ("single", "model (absolute)"),
        ("single", "z"),
    ]
    assert np.array_equal(out[0][3], m2.predict(Xq) >= 0.9)
    assert np.array_equal(out[1][3], Xq[:, 0] >= 1.0)
    assert np.array_equal(out[2][3], m1.predict(Xs) >= 0.8)
    assert np.array_equal(out[3][3], Xs[:, 0] >= 0.5)
    rows = [
        {
            "map": "m",
            "queries": "q",
            "mode": mode,
            "rule": rule,
            "threshold": thr,
            "result": oom.false_accepts(acc, np.ones(len(acc), bool)),
        }
        for mode, rule, thr, acc in out
    ]
    text = oom.table(rows)
    assert text.count("\n") == 5 and "| m | q (50) | single | model (absolute) | 0.8 |" in text
