"""Hierarchy.run on tiny hand-built databases (spec §5.1-5.3, docs/spec/fusion.md).

Each test gives fixed raw scores per method over a database of 6 images (indices 0..5) through a
``score_fn(method_id, subset)`` callback, and checks every tier, the final candidates F, the
Combined z-scores and the match / quality against values worked out by hand in the comments.

Notation: S_m = a method's normalised score (best 1, worst 0). For a distance,
S = (max - x) / (max - min); for a similarity, S = (x - min) / (max - min), with max / min taken
over the whole database at tier 1 and over the tier's input candidates at later tiers.
Combined: x_t = tier value at F (max over methods for non-final tiers, mean for the final tier),
min-max re-normalised over F and times w_t; Dsuper = sum_t x_t; z = zscore(Dsuper) with the
sample std (n - 1); match = F[argmax z], quality = max z.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import pytest

from hmpf.config import HierarchyConfig
from hmpf.hierarchy import Hierarchy, HierarchyResult, TierResult
from hmpf.methods import Method, create_method
from hmpf.methods.base import GlobalMethod

NAN = np.nan
MODES = ["default", "faithful"]


class _Distance(GlobalMethod):
    """Fake lower-is-better method: only ``higher_is_better`` is read by the hierarchy."""

    name = "test_distance"
    dim = 1
    higher_is_better = False

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.zeros(1)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        raise AssertionError("the hierarchy must score through score_fn only")


class _Similarity(_Distance):
    name = "test_similarity"
    higher_is_better = True


class _Scores:
    """score_fn over fixed raw arrays; records (method id, subset) of every call."""

    def __init__(self, raw: dict[str, Sequence[float]]) -> None:
        self.raw = {k: np.asarray(v, dtype=np.float64) for k, v in raw.items()}
        self.calls: list[tuple[str, np.ndarray | None]] = []

    def __call__(self, method_id: str, subset: np.ndarray | None) -> np.ndarray:
        self.calls.append((method_id, None if subset is None else np.array(subset)))
        r = self.raw[method_id]
        return r.copy() if subset is None else r[np.asarray(subset, dtype=np.int64)]

    def subsets(self, method_id: str) -> list[set[int] | None]:
        """The set of images scored per call of ``method_id`` (None: whole database)."""
        return [None if s is None else {int(i) for i in s} for m, s in self.calls if m == method_id]


def _config(
    tiers: Sequence[tuple[Sequence[str], int]], mode: str, weights: Sequence[float] | None = None
) -> HierarchyConfig:
    data: dict[str, Any] = {
        "mode": mode,
        "tiers": [{"methods": list(m), "k": k} for m, k in tiers],
    }
    if weights is not None:
        data["weights"] = list(weights)
    return HierarchyConfig.model_validate(data)


def _run(
    tiers: Sequence[tuple[Sequence[str], int]],
    raw: dict[str, Sequence[float]],
    mode: str,
    *,
    similarity: Iterable[str] = (),
    weights: Sequence[float] | None = None,
    methods: dict[str, Method] | None = None,
) -> tuple[HierarchyResult, _Scores]:
    cfg = _config(tiers, mode, weights)
    sims = set(similarity)
    if methods is None:
        methods = {m: (_Similarity() if m in sims else _Distance()) for m in cfg.method_ids}
    fn = _Scores(raw)
    n_db = len(next(iter(raw.values())))
    return Hierarchy(cfg, methods).run(fn, n_db), fn


def _off(mode: str) -> float:
    """Off-candidate entry of a later tier's full-length score: 0 (faithful) or NaN."""
    return 0.0 if mode == "faithful" else NAN


def _eq(actual: np.ndarray, expected: Sequence[float]) -> None:
    np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-12)


# Shared raw distances over 6 images.
A = [5, 1, 3, 9, 2, 7]  # min 1, max 9: S_A = (9 - x)/8 = [.5, 1, .75, 0, .875, .25]
S_A = [0.5, 1.0, 0.75, 0.0, 0.875, 0.25]


# ---------------------------------------------------------------------------------------------
# 2-tier and 3-tier hierarchies
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_two_tiers(mode: str) -> None:
    # Tier 1: a, b (distances), k=2 each. Tier 2: c (distance), k=1. Weights (.75, 1).
    raw = {
        "a": A,  # S_a = [.5, 1, .75, 0, .875, .25] -> top2 [1, 4]
        "b": [2, 6, 0, 8, 4, 10],  # min 0, max 10: S_b = (10 - x)/10
        #                           = [.8, .4, 1, .2, .6, 0] -> top2 [2, 0]
        "c": [3, 6, 1, 0, 4, 2],  # image 3 is c's best overall but never a candidate
    }
    res, fn = _run([(["a", "b"], 2), (["c"], 1)], raw, mode)
    t1, t2 = res.tiers

    assert t1.methods == ["a", "b"] and t1.inputs is None
    _eq(t1.scores["a"], S_A)
    _eq(t1.scores["b"], [0.8, 0.4, 1.0, 0.2, 0.6, 0.0])
    # union of [1, 4] and [2, 0]: no repeats, so the same in both modes
    np.testing.assert_array_equal(t1.candidates, [1, 4, 2, 0])

    # Tier 2 scores c only at [1, 4, 2, 0]: raw [6, 4, 1, 3], min 1, max 6, range 5
    #   S_c: img1 (6-6)/5 = 0, img4 (6-4)/5 = .4, img2 (6-1)/5 = 1, img0 (6-3)/5 = .6
    np.testing.assert_array_equal(t2.inputs, [1, 4, 2, 0])
    off = _off(mode)
    _eq(t2.scores["c"], [0.6, 0.0, 1.0, off, 0.4, off])
    np.testing.assert_array_equal(t2.candidates, [2])
    # The raw scores are kept beside the normalised ones (NaN where a tier did not score).
    _eq(t1.raw["a"], A)
    _eq(t1.raw["b"], raw["b"])
    _eq(t2.raw["c"], [3, 6, 1, NAN, 4, NAN])
    assert fn.subsets("a") == [None] and fn.subsets("b") == [None]
    assert fn.subsets("c") == [{0, 1, 2, 4}]

    # F = tier-1 candidates = [1, 4, 2, 0]
    # x1 = max(S_a, S_b) at F = [max(1,.4), max(.875,.6), max(.75,1), max(.5,.8)]
    #    = [1, .875, 1, .8] -> min .8, range .2 -> [1, .375, 1, 0] * .75
    #    = [.75, .28125, .75, 0]
    # x2 = S_c at F = [0, .4, 1, .6] (min 0, max 1: unchanged) * 1
    # Dsuper = [.75, .68125, 1.75, .6]; mean .9453125, sample sd .5399502050729617
    # z = [-.3617231703, -.4890497263, 1.4902994618, -.6395265651] -> j = 2, match F[2] = 2
    np.testing.assert_array_equal(res.final_candidates, [1, 4, 2, 0])
    _eq(
        res.combined,
        [-0.3617231703312495, -0.4890497262878493, 1.4902994617647478, -0.6395265651456491],
    )
    assert res.match == 2
    assert res.quality == pytest.approx(1.4902994617647478, abs=1e-12)


def test_two_tiers_explicit_weights() -> None:
    # Same data as test_two_tiers with weights (1, 1):
    # x1 = [1, .375, 1, 0] * 1, x2 = [0, .4, 1, .6] -> Dsuper = [1, .775, 2, .6]
    # mean 1.09375, sample sd .6259575997 -> z = [-.1497705277, -.5092197940, 1.4477817673,
    # -.7887914456]
    raw = {"a": A, "b": [2, 6, 0, 8, 4, 10], "c": [3, 6, 1, 0, 4, 2]}
    res, _ = _run([(["a", "b"], 2), (["c"], 1)], raw, "default", weights=[1.0, 1.0])
    _eq(
        res.combined,
        [-0.1497705276517287, -0.5092197940158775, 1.447781767300044, -0.7887914456324379],
    )
    assert res.match == 2


@pytest.mark.parametrize("mode", MODES)
def test_three_tiers_answer_is_not_final_tier_pick(mode: str) -> None:
    # Tier 1: a (distance) k=4. Tier 2: b (distance) + c (SIMILARITY) k=2 each.
    # Tier 3: d (distance) k=1. Weights (.5, .75, 1).
    raw = {
        "a": [0, 2, 4, 1, 8, 3],  # min 0, max 8: S_a = (8-x)/8 = [1, .75, .5, .875, 0, .625]
        #                              -> top4 [0, 3, 1, 5]
        "b": [6, 2, 9, 4, 0, 1],  # image 4 is b's best overall but never a candidate
        "c": [10, 0, 3, 30, 5, 5],  # similarity
        "d": [4, 3, 9, 1, 9, 0],
    }
    res, fn = _run([(["a"], 4), (["b", "c"], 2), (["d"], 1)], raw, mode, similarity=["c"])
    t1, t2, t3 = res.tiers
    off = _off(mode)

    _eq(t1.scores["a"], [1.0, 0.75, 0.5, 0.875, 0.0, 0.625])
    np.testing.assert_array_equal(t1.candidates, [0, 3, 1, 5])

    # Tier 2 over [0, 3, 1, 5]:
    #   b raw [6, 4, 2, 1]: min 1, max 6, range 5 -> img0 0, img3 .4, img1 .8, img5 1
    #     top2 [5, 1]
    #   c raw [10, 30, 0, 5] (similarity): min 0, max 30 -> img0 1/3, img3 1, img1 0, img5 1/6
    #     top2 [3, 0]
    np.testing.assert_array_equal(t2.inputs, [0, 3, 1, 5])
    _eq(t2.scores["b"], [0.0, 0.8, off, 0.4, off, 1.0])
    _eq(t2.scores["c"], [1 / 3, 0.0, off, 1.0, off, 1 / 6])
    np.testing.assert_array_equal(t2.candidates, [5, 1, 3, 0])

    # Tier 3 over [5, 1, 3, 0]: d raw [0, 3, 1, 4]: min 0, max 4 -> S_d = (4-x)/4:
    #   img5 1, img1 .25, img3 .75, img0 0 -> the final tier's own pick is 5
    np.testing.assert_array_equal(t3.inputs, [5, 1, 3, 0])
    _eq(t3.scores["d"], [0.0, 0.25, off, 0.75, off, 1.0])
    np.testing.assert_array_equal(t3.candidates, [5])
    assert fn.subsets("b") == [{0, 1, 3, 5}] and fn.subsets("c") == [{0, 1, 3, 5}]
    assert fn.subsets("d") == [{0, 1, 3, 5}]

    # F = tier-2 candidates = [5, 1, 3, 0]
    # x1 = S_a at F = [.625, .75, .875, 1] -> min .625, range .375 -> [0, 1/3, 2/3, 1] * .5
    #    = [0, 1/6, 1/3, .5]
    # x2 = max(S_b, S_c) at F = [max(1, 1/6), max(.8, 0), max(.4, 1), max(0, 1/3)]
    #    = [1, .8, 1, 1/3] -> min 1/3, range 2/3 -> [1, .7, 1, 0] * .75 = [.75, .525, .75, 0]
    # x3 = S_d at F = [1, .25, .75, 0] * 1
    # Dsuper = [1.75, .941667, 1.833333, .5]; mean 1.25625, sample sd .6449007604
    # z = [.7656216744, -.4878011512, .8948405224, -1.1726610456] -> j = 2, match 3
    np.testing.assert_array_equal(res.final_candidates, [5, 1, 3, 0])
    _eq(
        res.combined,
        [0.7656216744229822, -0.4878011512146424, 0.894840522426861, -1.1726610456352002],
    )
    assert res.match == 3
    assert res.quality == pytest.approx(0.894840522426861, abs=1e-12)


# ---------------------------------------------------------------------------------------------
# ties
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_ties_lower_index_wins(mode: str) -> None:
    raw = {
        "a": [4, 1, 2, 2, 5, 2],  # min 1, max 5: S_a = (5-x)/4 = [.25, 1, .75, .75, 0, .75]
        #                          top3: 1, then the tied .75s at 2, 3 (not 5) -> [1, 2, 3]
        "b": [0, 3, 1, 1, 0, 0],  # at [1, 2, 3]: [3, 1, 1] -> img1 0, img2 1, img3 1
        #                          top1: tie between 2 and 3 -> 2
    }
    res, _ = _run([(["a"], 3), (["b"], 1)], raw, mode)
    np.testing.assert_array_equal(res.tiers[0].candidates, [1, 2, 3])
    off = _off(mode)
    _eq(res.tiers[1].scores["b"], [off, 0.0, 1.0, 1.0, off, off])
    np.testing.assert_array_equal(res.tiers[1].candidates, [2])
    # F = [1, 2, 3]: x1 = [1, .75, .75] -> [1, 0, 0] * .75; x2 = [0, 1, 1]
    # Dsuper = [.75, 1, 1]; mean 11/12, deviations [-1/6, 1/12, 1/12], sample var 1/48
    # z = [-2, 1, 1]/sqrt(3); the tied maximum goes to the first: j = 1, match 2
    r3 = math.sqrt(3.0)
    _eq(res.combined, [-2 / r3, 1 / r3, 1 / r3])
    assert res.match == 2
    assert res.quality == pytest.approx(1 / r3, abs=1e-12)


def test_constant_tier_value_over_final_candidates() -> None:
    # Tier 1 a: S_a = (5-x)/4 = [.5, 1, .75, 1, 0, 1] -> top3 (ties by index) [1, 3, 5].
    # Tier 2 b at [1, 3, 5]: raw [4, 2, 2] -> img1 0, img3 1, img5 1 -> top1 [3].
    # x1 = S_a at F = [1, 1, 1]: constant.
    raw = {"a": [3, 1, 2, 1, 5, 1], "b": [0, 4, 0, 2, 0, 2]}
    # Default: constant -> ones * .75; Dsuper = [.75, 1.75, 1.75]
    #   mean 17/12, deviations [-2/3, 1/3, 1/3], sample var 1/3 -> z = [-2, 1, 1]/sqrt(3)
    res, _ = _run([(["a"], 3), (["b"], 1)], raw, "default")
    np.testing.assert_array_equal(res.final_candidates, [1, 3, 5])
    r3 = math.sqrt(3.0)
    _eq(res.combined, [-2 / r3, 1 / r3, 1 / r3])
    assert res.match == 3
    assert res.quality == pytest.approx(1 / r3, abs=1e-12)
    # Faithful: (x1 - min)/(max - min) = 0/0 = NaN, so Dsuper and z are all NaN, MATLAB's
    # max returns NaN at index 1: match F[0] = 1, quality NaN.
    res, _ = _run([(["a"], 3), (["b"], 1)], raw, "faithful")
    np.testing.assert_array_equal(res.final_candidates, [1, 3, 5])
    np.testing.assert_array_equal(res.tiers[1].candidates, [3])
    assert np.isnan(res.combined).all() and res.combined.shape == (3,)
    assert res.match == 1
    assert math.isnan(res.quality)


# ---------------------------------------------------------------------------------------------
# duplicate candidates
# ---------------------------------------------------------------------------------------------

DUP_RAW = {
    "a": A,  # S_a = [.5, 1, .75, 0, .875, .25] -> top2 [1, 4]
    "b": [4, 6, 0, 8, 2, 8],  # min 0, max 8: S_b = (8-x)/8 = [.5, .25, 1, 0, .75, 0]
    #                           -> top2 [2, 4]: image 4 is in both lists
    "c": [0, 2, 6, 0, 4, 0],  # at {1, 2, 4}: [2, 6, 4], min 2, max 6
    #                           -> img1 1, img2 0, img4 .5
}
DUP_TIERS = [(["a", "b"], 2), (["c"], 1)]


def test_duplicates_faithful_kept() -> None:
    res, fn = _run(DUP_TIERS, DUP_RAW, "faithful")
    # concatenation [1, 4] ++ [2, 4]
    np.testing.assert_array_equal(res.tiers[0].candidates, [1, 4, 2, 4])
    np.testing.assert_array_equal(res.tiers[1].inputs, [1, 4, 2, 4])
    _eq(res.tiers[1].scores["c"], [0.0, 1.0, 0.0, 0.0, 0.5, 0.0])
    np.testing.assert_array_equal(res.tiers[1].candidates, [1])
    assert fn.subsets("c") == [{1, 2, 4}]
    # F = [1, 4, 2, 4]
    # x1 = max(S_a, S_b) at F = [1, .875, 1, .875] -> [1, 0, 1, 0] * .75
    # x2 = S_c at F = [1, .5, 0, .5]
    # Dsuper = [1.75, .5, .75, .5]; mean .875, deviations [7/8, -3/8, -1/8, -3/8],
    # sample var (49 + 9 + 1 + 9)/64/3 = 17/48 -> z = deviations * sqrt(48/17)
    #   = [1.4702940882, -.6301260378, -.2100420126, -.6301260378]
    np.testing.assert_array_equal(res.final_candidates, [1, 4, 2, 4])
    s = math.sqrt(48 / 17)
    _eq(res.combined, [7 / 8 * s, -3 / 8 * s, -1 / 8 * s, -3 / 8 * s])
    assert res.match == 1
    assert res.quality == pytest.approx(7 / 8 * s, abs=1e-12)
    # ranking(): z order [0, 2, 1, 3] -> [1, 2, 4, 4] -> de-duplicated [1, 2, 4]
    np.testing.assert_array_equal(res.ranking(), [1, 2, 4])


def test_duplicates_default_removed() -> None:
    res, _ = _run(DUP_TIERS, DUP_RAW, "default")
    np.testing.assert_array_equal(res.tiers[0].candidates, [1, 4, 2])
    _eq(res.tiers[1].scores["c"], [NAN, 1.0, 0.0, NAN, 0.5, NAN])
    np.testing.assert_array_equal(res.tiers[1].candidates, [1])
    # F = [1, 4, 2]: x1 = [1, .875, 1] -> [1, 0, 1] * .75; x2 = [1, .5, 0]
    # Dsuper = [1.75, .5, .75]; mean 1, deviations [.75, -.5, -.25], sample var .875/2 = 7/16
    # z = [3, -2, -1]/sqrt(7)
    np.testing.assert_array_equal(res.final_candidates, [1, 4, 2])
    r7 = math.sqrt(7.0)
    _eq(res.combined, [3 / r7, -2 / r7, -1 / r7])
    assert res.match == 1
    assert res.quality == pytest.approx(3 / r7, abs=1e-12)


# ---------------------------------------------------------------------------------------------
# faithful zero scatter
# ---------------------------------------------------------------------------------------------

ZS_RAW = {
    "a": [9, 8, 7, 6, 1, 2],  # min 1, max 9: S_a = (9-x)/8 = [0, .125, .25, .375, 1, .875]
    #                          -> top2 [4, 5]
    "b": [0, 0, 0, 0, 3, 1],  # at [4, 5]: [3, 1] -> img4 0, img5 1
    "c": [2, 4, 9, 9, 5, 3],
}
ZS_TIERS = [(["a"], 2), (["b"], 3), (["c"], 1)]


def test_zero_scatter_faithful_admits_unseen_images() -> None:
    res, fn = _run(ZS_TIERS, ZS_RAW, "faithful")
    np.testing.assert_array_equal(res.tiers[0].candidates, [4, 5])
    # b full-length: [0, 0, 0, 0, 0 (img4, a real candidate), 1]; k=3 > 2 inputs:
    # top3 = 5, then the zeros by index: 0, 1 (images never seen by tier 1 beat image 4)
    _eq(res.tiers[1].scores["b"], [0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(res.tiers[1].candidates, [5, 0, 1])
    # Tier 3 scores c at [5, 0, 1]: raw [3, 2, 4], min 2, max 4 -> img5 .5, img0 1, img1 0
    assert fn.subsets("c") == [{0, 1, 5}]
    _eq(res.tiers[2].scores["c"], [1.0, 0.0, 0.0, 0.0, 0.0, 0.5])
    np.testing.assert_array_equal(res.tiers[2].candidates, [0])
    # F = [5, 0, 1]; weights (.5, .75, 1)
    # x1 = S_a at F = [.875, 0, .125] -> min 0, range .875 -> [1, 0, 1/7] * .5 = [.5, 0, 1/14]
    # x2 = S_b at F = [1, 0, 0] * .75
    # x3 = S_c at F = [.5, 1, 0]
    # Dsuper = [1.75, 1, 1/14]; mean .9404761905, sample sd .8408673041
    # z = [.9627248028, .0707885884, -1.0335133912] -> match 5
    np.testing.assert_array_equal(res.final_candidates, [5, 0, 1])
    _eq(res.combined, [0.9627248027868515, 0.0707885884402095, -1.0335133912270613])
    assert res.match == 5
    assert res.quality == pytest.approx(0.9627248027868515, abs=1e-12)


def test_zero_scatter_default_does_not() -> None:
    res, fn = _run(ZS_TIERS, ZS_RAW, "default")
    np.testing.assert_array_equal(res.tiers[0].candidates, [4, 5])
    # off-candidate entries are NaN, skipped: only 2 entries to pick from -> [5, 4]
    _eq(res.tiers[1].scores["b"], [NAN, NAN, NAN, NAN, 0, 1])
    np.testing.assert_array_equal(res.tiers[1].candidates, [5, 4])
    # Tier 3 c at [5, 4]: raw [3, 5] -> img5 1, img4 0
    assert fn.subsets("c") == [{4, 5}]
    np.testing.assert_array_equal(res.tiers[2].candidates, [5])
    # F = [5, 4]: x1 = [.875, 1] -> [0, 1] * .5; x2 = [1, 0] * .75; x3 = [1, 0]
    # Dsuper = [1.75, .5] -> z = [1, -1]/sqrt(2)
    np.testing.assert_array_equal(res.final_candidates, [5, 4])
    h = 1 / math.sqrt(2.0)
    _eq(res.combined, [h, -h])
    assert res.match == 5
    assert res.quality == pytest.approx(h, abs=1e-12)


# ---------------------------------------------------------------------------------------------
# a single candidate
# ---------------------------------------------------------------------------------------------

SINGLE_RAW = {"a": A, "b": [3, 8, 1, 0, 2, 5]}  # tier 1: S_a top1 = [1]
SINGLE_TIERS = [(["a"], 1), (["b"], 1)]


def test_single_candidate_faithful_nan() -> None:
    res, _ = _run(SINGLE_TIERS, SINGLE_RAW, "faithful")
    np.testing.assert_array_equal(res.tiers[0].candidates, [1])
    # b over [1] is a constant: 0/0 = NaN at image 1, zeros elsewhere; top1 skips the NaN
    # and takes the first zero: image 0.
    _eq(res.tiers[1].scores["b"], [0, NAN, 0, 0, 0, 0])
    np.testing.assert_array_equal(res.tiers[1].candidates, [0])
    # F = [1]: every x_t is a constant -> NaN; z NaN; match F[0] = 1, quality NaN
    np.testing.assert_array_equal(res.final_candidates, [1])
    assert res.combined.shape == (1,) and np.isnan(res.combined).all()
    assert res.match == 1
    assert math.isnan(res.quality)


def test_single_candidate_default() -> None:
    res, _ = _run(SINGLE_TIERS, SINGLE_RAW, "default")
    # b over [1] is a constant -> 1 (equally the best)
    _eq(res.tiers[1].scores["b"], [NAN, 1, NAN, NAN, NAN, NAN])
    np.testing.assert_array_equal(res.tiers[1].candidates, [1])
    # F = [1]: x1 = 1 * .75, x2 = 1 -> Dsuper [1.75]; zscore of one entry -> 0
    np.testing.assert_array_equal(res.final_candidates, [1])
    _eq(res.combined, [0.0])
    assert res.match == 1
    assert res.quality == 0.0


# ---------------------------------------------------------------------------------------------
# same method in two tiers, one tier, direction
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", MODES)
def test_same_method_in_two_tiers(mode: str) -> None:
    # a at tier 1 (whole database) then again at tier 2 (re-normalised over its candidates).
    cfg = _config([(["a"], 3), (["a"], 1)], mode)
    assert cfg.method_ids == ["a"]
    res, fn = _run([(["a"], 3), (["a"], 1)], {"a": A}, mode)
    # Tier 1: S_a = [.5, 1, .75, 0, .875, .25] -> top3 [1, 4, 2]
    _eq(res.tiers[0].scores["a"], S_A)
    np.testing.assert_array_equal(res.tiers[0].candidates, [1, 4, 2])
    # Tier 2: a over [1, 4, 2]: raw [1, 2, 3], min 1, max 3 -> img1 1, img4 .5, img2 0
    off = _off(mode)
    _eq(res.tiers[1].scores["a"], [off, 1.0, 0.0, off, 0.5, off])
    np.testing.assert_array_equal(res.tiers[1].candidates, [1])
    assert fn.subsets("a") == [None, {1, 2, 4}]
    # F = [1, 4, 2]: x1 = [1, .875, .75] -> [1, .5, 0] * .75 = [.75, .375, 0]; x2 = [1, .5, 0]
    # Dsuper = [1.75, .875, 0]; mean .875, deviations [.875, 0, -.875], sample sd .875
    # z = [1, 0, -1]
    _eq(res.combined, [1.0, 0.0, -1.0])
    assert res.match == 1
    assert res.quality == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_one_tier_final_candidates_are_whole_database(mode: str) -> None:
    # Real registered methods as ids (only higher_is_better = False is read).
    methods = {"hog": create_method("hog"), "gist": create_method("gist")}
    raw = {
        "hog": A,  # S = [.5, 1, .75, 0, .875, .25]
        "gist": [4, 6, 0, 8, 2, 8],  # S = (8-x)/8 = [.5, .25, 1, 0, .75, 0]
    }
    res, _ = _run([(["hog", "gist"], 2)], raw, mode, methods=methods)
    (t1,) = res.tiers
    assert t1.inputs is None
    # mean = [.5, .625, .875, 0, .8125, .125] -> top2 [2, 4]
    np.testing.assert_array_equal(t1.candidates, [2, 4])
    # F = all 6 images, weight (1,): x1 = mean / .875 = [4/7, 5/7, 1, 0, 13/14, 1/7]
    # mean 47/84 = .5595238095, sample sd .4101186157
    # z = [.0290276068, .3773588880, 1.0740214505, -1.3642975182, .8998558099, -1.0159662370]
    np.testing.assert_array_equal(res.final_candidates, np.arange(6))
    _eq(
        res.combined,
        [
            0.0290276067707369,
            0.3773588880195807,
            1.074021450517268,
            -1.364297518224638,
            0.8998558098928463,
            -1.0159662369757942,
        ],
    )
    assert res.match == 2
    assert res.quality == pytest.approx(1.074021450517268, abs=1e-12)


@pytest.mark.parametrize("mode", MODES)
def test_higher_is_better_direction(mode: str) -> None:
    raw = {
        "s": [5, 9, 7, 1, 8, 3],  # similarity = 10 - A: min 1, max 9, S = (x-1)/8
        #                          = [.5, 1, .75, 0, .875, .25] -> top3 [1, 4, 2]
        "t": [9, 2, 4, 9, 3, 9],  # similarity at [1, 4, 2]: [2, 3, 4], min 2, max 4
        #                          -> img1 0, img4 .5, img2 1 -> top1 [2]
    }
    res, _ = _run([(["s"], 3), (["t"], 1)], raw, mode, similarity=["s", "t"])
    _eq(res.tiers[0].scores["s"], S_A)
    np.testing.assert_array_equal(res.tiers[0].candidates, [1, 4, 2])
    off = _off(mode)
    _eq(res.tiers[1].scores["t"], [off, 0.0, 1.0, off, 0.5, off])
    np.testing.assert_array_equal(res.tiers[1].candidates, [2])
    # F = [1, 4, 2]: x1 = [1, .875, .75] -> [1, .5, 0] * .75; x2 = [0, .5, 1]
    # Dsuper = [.75, .875, 1]; mean .875, sample sd .125 -> z = [-1, 0, 1]
    _eq(res.combined, [-1.0, 0.0, 1.0])
    assert res.match == 2
    assert res.quality == pytest.approx(1.0, abs=1e-12)

    # The same hierarchy with the scores as distances (10 - x) gives the same answer.
    dist = {k: [10 - v for v in vals] for k, vals in raw.items()}
    res_d, _ = _run([(["s"], 3), (["t"], 1)], dist, mode)
    np.testing.assert_array_equal(res_d.final_candidates, res.final_candidates)
    _eq(res_d.combined, res.combined)
    assert res_d.match == res.match


# ---------------------------------------------------------------------------------------------
# small pieces
# ---------------------------------------------------------------------------------------------


def test_missing_method_instance_rejected() -> None:
    cfg = _config([(["a"], 2), (["b"], 1)], "default")
    with pytest.raises(ValueError, match="b"):
        Hierarchy(cfg, {"a": _Distance()})


def test_tier_result_mean_and_max() -> None:
    tr = TierResult(
        methods=["x", "y"],
        inputs=None,
        scores={"x": np.array([NAN, 0.2, NAN, 0.9]), "y": np.array([NAN, NAN, 0.5, 0.4])},
        candidates=np.zeros(0, np.int64),
        time_ms=0.0,
    )
    # max ignores NaN unless both are NaN: [NaN, .2, .5, .9]
    _eq(tr.max_score(), [NAN, 0.2, 0.5, 0.9])
    # mean propagates NaN: [NaN, NaN, NaN, .65]
    _eq(tr.mean_score(), [NAN, NAN, NAN, 0.65])


def test_tier_score_mean_changes_the_answer() -> None:
    # Default mode (the faithful union would list image 1 twice).
    # Tier 1: a, b (distances), k=2 each; tier 2: c (distance), k=1; weights (.75, 1).
    #   S_a = (10 - x)/10 = [1, .8, 0, 0] -> top2 [0, 1]
    #   S_b = [0, .8, 1, 0]               -> top2 [2, 1]; F = union = [0, 1, 2]
    #   c over F: raw [1, 1, 5] -> S_c = [1, 1, 0] (x2)
    # max:  x1 = [1, .8, 1] -> [1, 0, 1] * .75; Dsuper = [1.75, 1, .75] -> image 0
    # mean: x1 = [.5, .8, .5] -> [0, 1, 0] * .75; Dsuper = [1, 1.75, 0] -> image 1,
    #       mean 2.75/3, sample sd sqrt(.7708333) = .8779711 -> quality .8333333/.8779711
    raw = {"a": [0, 2, 10, 10], "b": [10, 2, 0, 10], "c": [1, 1, 5, 0]}
    tiers = [(["a", "b"], 2), (["c"], 1)]
    by_max, _ = _run(tiers, raw, "default")
    assert by_max.match == 0
    cfg = _config(tiers, "default").model_copy(update={"tier_score": "mean"})
    methods: dict[str, Method] = {m: _Distance() for m in "abc"}
    by_mean = Hierarchy(cfg, methods).run(_Scores(raw), 4)
    np.testing.assert_array_equal(by_mean.final_candidates, [0, 1, 2])
    assert by_mean.match == 1
    assert by_mean.quality == pytest.approx((1.75 - 2.75 / 3) / math.sqrt(0.7708333333333334))
    # the tiers themselves (scores, candidates) do not depend on tier_score
    for t_max, t_mean in zip(by_max.tiers, by_mean.tiers, strict=True):
        np.testing.assert_array_equal(t_max.candidates, t_mean.candidates)
