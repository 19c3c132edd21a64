"""The score bank's batch path (:mod:`hmpf.evaluation.batch`) against the per-query
hierarchy, bit for bit: random banks (ties, NaN, constant rows, k past the map), every shape
of hierarchy the search builds, both tier-score rules."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from hmpf.config import HierarchyConfig
from hmpf.evaluation.batch import batch_outcome
from hmpf.evaluation.metrics import HierarchyOutcome, outcome_of
from hmpf.evaluation.study import ScoreBank
from hmpf.methods import create_method

#: Four distances and a similarity (the batch reads ``higher_is_better`` only).
METHODS = {m: create_method(m) for m in ("hog", "gist", "sad", "kaze", "olo")}


def _bank(rng: np.random.Generator, nq: int, n_db: int, kind: str) -> ScoreBank:
    scores: dict[str, np.ndarray] = {}
    for mid in METHODS:
        x = rng.normal(size=(nq, n_db))
        if kind in ("ties", "nan"):
            x = np.round(x, 1)  # many equal scores: the order of ties decides
        if kind == "nan":
            x[rng.random(x.shape) < 0.05] = np.nan
            x[0] = np.nan  # a query no method could score
        if kind == "constant":
            x[rng.random(nq) < 0.3] = 0.25  # every reference alike for some queries
        scores[mid] = x
    gt = np.abs(np.arange(nq)[:, None] * n_db // nq - np.arange(n_db)[None, :]) <= 2
    return ScoreBank(dict(METHODS), scores, gt, data=None)  # type: ignore[arg-type]


def _config(rng: np.random.Generator, n_db: int) -> HierarchyConfig:
    n_tiers = int(rng.integers(1, 4))
    tiers: list[dict[str, Any]] = []
    for t in range(n_tiers):
        size = int(rng.integers(1, 4))
        chosen = rng.choice(list(METHODS), size=size, replace=False).tolist()
        k = int(rng.choice([1, 2, 3, 5, 10, n_db + 5])) if t < n_tiers - 1 else 1
        tiers.append({"methods": chosen, "k": k})
    data: dict[str, Any] = {"tiers": tiers, "tier_score": str(rng.choice(["max", "mean"]))}
    if rng.random() < 0.5:
        data["weights"] = rng.uniform(0.1, 1.0, size=n_tiers).round(2).tolist()
    return HierarchyConfig.model_validate(data)


def _per_query(bank: ScoreBank, config: HierarchyConfig) -> HierarchyOutcome:
    return outcome_of(bank.results(config), bank.gt, bank.n_db)


def _same(fast: HierarchyOutcome, slow: HierarchyOutcome) -> None:
    np.testing.assert_array_equal(fast.matches, slow.matches)
    np.testing.assert_array_equal(fast.quality, slow.quality)  # NaN == NaN, floats exact
    np.testing.assert_array_equal(fast.correct, slow.correct)
    assert fast.tier_top1 == slow.tier_top1
    assert fast.tier_recall == slow.tier_recall
    assert fast.mean_inputs == slow.mean_inputs
    assert fast.mean_candidates == slow.mean_candidates


@pytest.mark.parametrize("kind", ["plain", "ties", "nan", "constant"])
def test_batch_equals_the_per_query_hierarchy(kind: str) -> None:
    rng = np.random.default_rng(["plain", "ties", "nan", "constant"].index(kind))
    shapes = set()
    for _ in range(60):
        bank = _bank(rng, nq=int(rng.integers(5, 30)), n_db=int(rng.integers(3, 50)), kind=kind)
        config = _config(rng, bank.n_db)
        fast = batch_outcome(config, bank.methods, bank.scores, bank.gt)
        assert fast is not None
        _same(fast, _per_query(bank, config))
        shapes.add((len(config.tiers), config.tier_score))
        assert np.isnan(fast.tier_ms).all() and np.isnan(fast.fusion_ms)  # not timed
    assert len(shapes) == 6  # 1-3 tiers, both rules


def test_a_single_candidate_and_a_single_reference() -> None:
    rng = np.random.default_rng(7)
    bank = _bank(rng, nq=6, n_db=1, kind="plain")
    for tiers in ([["hog"]], [["hog", "olo"], ["gist"]], [["sad"], ["olo"], ["kaze"]]):
        data = {"tiers": [{"methods": m, "k": 1} for m in tiers]}
        config = HierarchyConfig.model_validate(data)
        fast = batch_outcome(config, bank.methods, bank.scores, bank.gt)
        assert fast is not None and (fast.matches == 0).all()
        _same(fast, _per_query(bank, config))


def test_bank_run_takes_the_batch_and_faithful_mode_runs_per_query() -> None:
    rng = np.random.default_rng(3)
    bank = _bank(rng, nq=12, n_db=40, kind="ties")
    tiers = [{"methods": ["hog", "olo"], "k": 5}, {"methods": ["gist"], "k": 1}]
    default = HierarchyConfig.model_validate({"tiers": tiers})
    out = bank.run(default)
    assert np.isnan(out.fusion_ms)  # the batch (not timed)
    _same(out, _per_query(bank, default))
    faithful = HierarchyConfig.model_validate({"tiers": tiers, "mode": "faithful"})
    assert batch_outcome(faithful, bank.methods, bank.scores, bank.gt) is None
    out = bank.run(faithful)
    assert not np.isnan(out.fusion_ms)  # per query, timed
    _same(out, _per_query(bank, faithful))


def test_chunks_and_whole_map_unions_give_the_same_floats() -> None:
    """Queries run in chunks (here of 3-4 queries) and a first tier passing on every
    reference of a larger map (the union of three whole lists, the paper's "flat" setting):
    the per-query figures still, with no (queries x list x list) comparison made."""
    rng = np.random.default_rng(11)
    bank = _bank(rng, nq=10, n_db=600, kind="ties")
    tiers = [{"methods": ["hog", "olo", "gist"], "k": 600}, {"methods": ["sad"], "k": 1}]
    config = HierarchyConfig.model_validate({"tiers": tiers})
    slow = _per_query(bank, config)
    for entries in (2000, 1 << 21):  # 3 queries per chunk, then one chunk
        fast = batch_outcome(config, bank.methods, bank.scores, bank.gt, chunk_entries=entries)
        assert fast is not None
        _same(fast, slow)
    assert fast.mean_inputs == [600.0, 600.0]


def test_an_empty_bank_is_an_empty_outcome() -> None:
    scores = {m: np.zeros((0, 5)) for m in METHODS}
    config = HierarchyConfig.model_validate({"tiers": [{"methods": ["hog"], "k": 1}]})
    fast = batch_outcome(config, METHODS, scores, np.zeros((0, 5), bool))
    assert fast is not None and len(fast.matches) == 0 and fast.recall_at_1 == 0.0
