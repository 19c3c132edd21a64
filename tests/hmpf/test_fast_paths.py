"""Fast paths for maps of a million references against their brute-force definitions:
top-k through block maxima, later tiers kept as entries (:class:`~hmpf.fusion.Spread`),
tier 1's best rival from its highest scores, an approximate tier 1 kept as entries and a
fill (:class:`~hmpf.fusion.Filled`). Each must give exactly what the whole-array
computation gives (tier 1's z-score: to rounding, its mean summed another way)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmpf.confidence import ReferenceProfile, _best_outside, _best_outside_all, answer_features
from hmpf.config import parse_config
from hmpf.fusion import Filled, Spread, mean_of, minmax_normalise, top_k
from hmpf.hierarchy import Hierarchy, HierarchyResult, TierResult
from hmpf.methods import create_method
from hmpf.sequence import Evidence, RouteMap


def _top_k_definition(s: np.ndarray, k: int) -> np.ndarray:
    """Highest first, ties to the lower index, NaN skipped: a full stable sort."""
    valid = np.flatnonzero(~np.isnan(s))
    order = valid[np.lexsort((valid, -s[valid]))]
    return order[:k]


@pytest.mark.parametrize("n", [10, 1000, 20_000, 300_000])
@pytest.mark.parametrize("kind", ["random", "ties", "constant_floor", "nan"])
def test_top_k_equals_a_full_sort(n, kind):
    rng = np.random.default_rng(n)
    s = rng.random(n)
    if kind == "ties":
        s = np.round(s * 20) / 20  # many equal values, also at the cut
    elif kind == "constant_floor":  # an approximate tier 1: a few scored, the rest the worst
        s = np.full(n, 0.0)
        s[rng.choice(n, min(n, 1300), replace=False)] = rng.random(min(n, 1300))
    elif kind == "nan":
        s[rng.random(n) < 0.3] = np.nan
    for k in (1, 10, 100, 255):
        assert np.array_equal(top_k(s, k), _top_k_definition(s, k)), (kind, k)


def test_spread_reads_as_its_whole_array():
    rng = np.random.default_rng(1)
    idx = np.sort(rng.choice(5000, 40, replace=False))
    vals = {"a": rng.random(40), "b": np.where(rng.random(40) < 0.5, np.nan, rng.random(40))}
    vals["b"][:] = np.nan
    vals["b"][[3, 9, 30]] = [0.5, 0.7, 0.7]  # the best twice: the lower index wins
    sp = Spread(5000, idx, vals)
    for m, v in vals.items():
        whole = np.full(5000, np.nan)
        whole[idx] = v
        assert np.array_equal(sp[m], whole, equal_nan=True)
        probe = np.concatenate([idx[::3], rng.integers(0, 5000, 50)])
        assert np.array_equal(sp.at(m, probe), whole[probe], equal_nan=True)
        assert sp.best(m) == int(np.nanargmax(whole))
    assert Spread(10, np.array([2]), {"c": np.array([np.nan])}).best("c") == -1
    assert sorted(sp) == ["a", "b"] and len(sp) == 2
    as_dict = dict(sp.items())  # a Mapping like the dict a tier held before
    assert list(as_dict) == ["a", "b"] and all(len(v) == 5000 for v in sp.values())


def _whole(result: HierarchyResult) -> HierarchyResult:
    """The same result with every tier's scores as whole arrays (what the tiers held
    before they kept entries)."""
    tiers = [
        TierResult(
            t.methods,
            t.inputs,
            {m: t.scores[m] for m in t.scores},
            t.candidates,
            t.time_ms,
            {m: t.raw[m] for m in t.raw},
        )
        for t in result.tiers
    ]
    return HierarchyResult(
        result.match, result.quality, result.final_candidates, result.combined, tiers
    )


def test_answer_features_are_the_same_from_entries_and_whole_arrays():
    config = parse_config(
        {
            "name": "fast-paths",
            "tiers": [{"methods": ["gist", "hog"], "k": 8}, {"methods": ["sad", "hog"], "k": 1}],
        }
    )
    methods = {m: create_method(m) for m in ("gist", "hog", "sad")}
    n = 50_000
    rng = np.random.default_rng(2)
    full = {m: rng.random(n) for m in ("gist", "hog")}

    def score_fn(mid, subset):
        x = full.get(mid, full["hog"][::-1].copy())
        return x if subset is None else x[subset]

    routes = RouteMap.from_metadata(n, sequence=np.repeat(np.arange(50), 1000))
    result = Hierarchy(config, methods).run(score_fn, n)
    assert isinstance(result.tiers[1].scores, Spread)
    got = answer_features(result, routes)
    want = answer_features(_whole(result), routes)
    assert got == want


def test_best_rival_from_the_highest_scores_equals_every_reference():
    rng = np.random.default_rng(3)
    n = 20_000
    routes = RouteMap.from_metadata(n, sequence=np.repeat(np.arange(20), 1000))
    for trial in range(20):
        v = rng.random(n)
        answer = int(rng.integers(n))
        if trial % 2:  # the answer's own neighbourhood holds the highest values
            lo = max(0, answer - 2)
            v[lo : answer + 3] = 2.0 + rng.random(len(v[lo : answer + 3]))
        for window in (0, 2, 5):
            assert _best_outside_all(v, answer, routes, window) == _best_outside(
                v, np.arange(n), answer, routes, window
            )


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_a_tiers_mean_score_is_numpys_mean_of_the_stack(count):
    rng = np.random.default_rng(count)
    n = 10_007
    scores = {f"m{i}": rng.random(n) for i in range(count)}
    for i, x in enumerate(scores.values()):
        x[rng.random(n) < 0.1 * i] = np.nan
    tier = TierResult(list(scores), None, scores, np.zeros(0, np.int64), 0.0)
    stack = np.stack(list(scores.values()))
    mean = tier.mean_score()
    assert np.array_equal(mean, np.mean(stack, axis=0), equal_nan=True)
    at = rng.integers(0, n, 300)
    assert np.array_equal(tier.mean_score(at), np.mean(stack[:, at], axis=0), equal_nan=True)
    mean[:] = -1.0  # a result of its own: the tier's arrays are not written
    assert np.array_equal(np.stack(list(scores.values())), stack, equal_nan=True)


def _tier1_definition(result: HierarchyResult, routes: RouteMap, window: int) -> dict:
    """Tier 1's features as whole-array passes, NaN and inf replaced at every step."""
    mean = np.mean([result.tiers[0].scores[m] for m in result.tiers[0].methods], axis=0)
    at = float(mean[result.match])
    rank = int(np.sum(np.where(np.isfinite(mean), mean, -np.inf) > at))
    score0 = np.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0)
    rival = _best_outside(score0, np.arange(len(mean)), result.match, routes, window)
    fin = mean[np.isfinite(mean)]
    return {
        "tier1_rank": math.log1p(rank),
        "tier1_margin": float(score0[result.match]) - (0.0 if rival is None else rival),
        "tier1_z": (at - float(fin.mean())) / float(fin.std()),
    }


@pytest.mark.parametrize("kind", ["finite", "nan", "inf"])
def test_tier1_features_equal_their_whole_array_definition(kind):
    rng = np.random.default_rng(4)
    n = 30_000
    routes = RouteMap.from_metadata(n, sequence=np.repeat(np.arange(30), 1000))
    for trial in range(5):
        scores = {"a": rng.random(n), "b": rng.random(n)}
        if kind != "finite":
            bad = rng.choice(n, 500, replace=False)
            scores["b"][bad] = np.nan if kind == "nan" else np.inf * rng.choice([-1, 1], 500)
        match = int(rng.integers(n))
        scores["a"][match] = scores["b"][match] = 0.99
        tier = TierResult(["a", "b"], None, scores, np.array([match]), 0.0)
        result = HierarchyResult(match, 1.0, np.array([match]), np.array([1.0]), [tier])
        got = answer_features(result, routes)
        for name, value in _tier1_definition(result, routes, 2).items():
            assert got[name] == value, (kind, trial, name)


def _filled(rng: np.random.Generator, n: int, kind: str, hib: bool = True) -> Filled:
    """An approximate tier 1's raw scores: a sample and candidates scored, the rest their
    worst (the lowest similarity, the highest distance)."""
    m = n if kind == "covers_all" else min(n, 1300)
    index = np.sort(rng.choice(n, m, replace=False))
    values = rng.random(m) + 0.5
    if kind == "ties":
        values = np.round(values * 10) / 10
    worst = float(values.min() if hib else values.max())
    if kind == "covers_all":  # a fill no reference holds: it must not count
        worst += -1.0 if hib else 1.0
    if kind == "few_above":  # fewer entries than k beat the fill: the fill decides ties
        values = np.full(m, worst)
        values[:5] = worst + 1.0 if hib else worst - 1.0
    if kind == "nan":
        values[rng.random(m) < 0.2] = np.nan
    return Filled(n, index, values, worst)


KINDS = ["approx", "ties", "few_above", "covers_all", "nan"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", [3000, 200_000])
def test_a_filled_vector_normalises_selects_and_averages_as_its_whole_array(kind, n):
    rng = np.random.default_rng(n + len(kind))
    for hib in (True, False):
        raw = _filled(rng, n, kind, hib)
        whole = np.asarray(raw)
        assert whole.shape == (n,) and len(raw) == n
        assert np.array_equal(raw.at(np.arange(n)), whole, equal_nan=True)
        for faithful in (False, True):
            got = minmax_normalise(raw, hib, faithful=faithful)
            want = minmax_normalise(whole, hib, faithful=faithful)
            assert np.array_equal(np.asarray(got), want, equal_nan=True), (hib, faithful)
        norm = minmax_normalise(raw, hib)
        for k in (1, 10, 100, 255):
            assert np.array_equal(top_k(norm, k), _top_k_definition(np.asarray(norm), k)), k
        # Two or three methods, each with its own entries: their mean over the union.
        others = [minmax_normalise(_filled(rng, n, kind), True) for _ in range(2)]
        for vectors in ([norm, others[0]], [norm, *others]):
            mean = mean_of(vectors)
            stack = np.stack([np.asarray(v) for v in vectors])
            assert np.array_equal(np.asarray(mean), np.mean(stack, axis=0), equal_nan=True)
        spread = Spread.of_filled(n, {"a": norm, "b": others[0]})
        probe = rng.integers(0, n, 500)
        for mid, v in (("a", norm), ("b", others[0])):
            dense = np.asarray(v)
            assert np.array_equal(spread[mid], dense, equal_nan=True)
            assert np.array_equal(spread.at(mid, probe), dense[probe], equal_nan=True)
            assert np.array_equal(np.asarray(spread.filled(mid)), dense, equal_nan=True)
            fin = np.isfinite(dense)
            best = int(np.nanargmax(np.where(fin, dense, np.nan))) if fin.any() else -1
            assert spread.best(mid) == best


class _Fill:
    """A score function whose whole-map scores are :class:`Filled` vectors (an approximate
    tier 1), or their whole arrays."""

    def __init__(self, vectors: dict[str, Filled], whole: bool) -> None:
        self.vectors, self.whole = vectors, whole

    def __call__(self, mid, subset):
        v = self.vectors[mid]
        if subset is None:
            return np.asarray(v) if self.whole else v
        return v.at(subset)


@pytest.mark.parametrize("kind", ["approx", "ties", "covers_all"])
def test_an_approximate_tier1_answers_as_its_whole_arrays(kind):
    """The hierarchy on Filled tier-1 scores against the same scores as whole arrays: the
    same answer, tiers, fusion and confidence features (tier 1's z to rounding) and the
    same reference-profile z."""
    config = parse_config(
        {
            "name": "filled",
            "tiers": [{"methods": ["gist", "hog"], "k": 8}, {"methods": ["sad", "hog"], "k": 1}],
        }
    )
    methods = {m: create_method(m) for m in ("gist", "hog", "sad")}
    n = 60_000
    routes = RouteMap.from_metadata(n, sequence=np.repeat(np.arange(60), 1000))
    rng = np.random.default_rng(5)
    for trial in range(4):
        vectors = {
            "gist": _filled(rng, n, kind, hib=methods["gist"].higher_is_better),
            "hog": _filled(rng, n, kind, hib=methods["hog"].higher_is_better),
        }
        vectors["sad"] = Filled(n, np.arange(n), rng.random(n), 0.0)
        hierarchy = Hierarchy(config, methods)
        got = hierarchy.run(_Fill(vectors, whole=False), n)
        want = hierarchy.run(_Fill(vectors, whole=True), n)
        if kind != "covers_all":
            assert isinstance(got.tiers[0].scores, Spread)
        assert (got.match, got.quality) == (want.match, want.quality)
        assert np.array_equal(got.combined, want.combined)
        assert np.array_equal(got.final_candidates, want.final_candidates)
        for a, b in zip(got.tiers, want.tiers, strict=True):
            assert np.array_equal(a.candidates, b.candidates)
            for m in a.methods:
                assert np.array_equal(a.scores[m], b.scores[m], equal_nan=True)
                assert np.array_equal(a.raw[m], b.raw[m], equal_nan=True)
        assert np.array_equal(got.tiers[0].mean_score(), want.tiers[0].mean_score())
        f_got, f_want = answer_features(got, routes), answer_features(want, routes)
        assert f_got.keys() == f_want.keys()
        for name in f_got:
            if name == "tier1_z":
                assert f_got[name] == pytest.approx(f_want[name], rel=1e-9, abs=1e-12)
            else:
                assert f_got[name] == f_want[name], (trial, name)
        profile = ReferenceProfile(
            ("gist", "hog"), (1.0, -1.0), rng.random((2, n)), rng.random((2, n)) + 0.1
        )
        for ref in (got.match, int(rng.integers(n)), int(vectors["hog"].index[0])):
            assert profile.z(got.tiers[0].raw, ref) == profile.z(want.tiers[0].raw, ref)
        # The sequence filter's evidence: the same proposals and tier-1 scores at any refs.
        e_got, e_want = Evidence.from_result(got, n), Evidence.from_result(want, n)
        assert np.array_equal(e_got.proposals, e_want.proposals)
        refs = np.concatenate([rng.integers(0, n, 2000), vectors["gist"].index[:50]])
        assert np.array_equal(e_got.tier1_at(refs), e_want.tier1_at(refs))
