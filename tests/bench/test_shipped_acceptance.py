"""bench/shipped_acceptance.py's as-decided training figures on synthetic answers."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from hmpf.evaluation.acceptance import Answers, RoutePart
from hmpf.sequence import Estimate

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sa():
    path = ROOT / "bench" / "shipped_acceptance.py"
    spec = importlib.util.spec_from_file_location("bench_shipped_acceptance", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _answers(sa, correct: np.ndarray, rng: np.random.Generator, shift: float) -> Answers:
    n = len(correct)
    feats = [
        {
            name: float(rng.normal(shift * (2 * c - 1), 1.0))
            for name in sorted({*sa.SEQUENCE_FEATURES, *sa.SINGLE_FEATURES})
        }
        for c in correct
    ]
    ests = [Estimate(i % 50, 0.9, False, i + 1, continuous=i > 0) for i in range(n)]
    return Answers(feats, correct, np.zeros(n), np.arange(n), ests, np.zeros(n, np.int64))


def test_as_decided_gives_each_route_with_and_without_the_stay(sa):
    rng = np.random.default_rng(0)
    parts = []
    for name in ("a", "b", "c"):
        y = rng.random(200) < 0.7
        inside = _answers(sa, y, rng, 1.5)
        outside = _answers(sa, np.zeros(60, bool), rng, 1.5)
        parts.append(RoutePart(name, inside, outside))
    policy, train = sa.fit(parts, parts)
    got = train["sequence"]["as_decided"]
    assert set(got) == {"a", "b", "c"}
    for row in got.values():
        stay, entry = row["with_stay"], row["entry_only"]
        # the stay only keeps accepted estimates on: it accepts at least what entry does
        assert stay["accepted"] >= entry["accepted"]
        assert 0.0 <= entry["outside_accepted"] <= stay["outside_accepted"] <= 1.0
        for fig in (stay, entry):
            assert fig["precision"] is None or 0.0 <= fig["precision"] <= 1.0
    assert policy.sequence_stay_threshold == min(sa.STAY_P, policy.sequence_threshold)
