"""Hand-computed toy cases for the pure fusion functions (spec §5, docs/spec/fusion.md).

Every expected value below is worked out by hand in the comments; nothing is derived by
calling the function under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmpf.fusion import (
    DEFAULT_WEIGHTS,
    combined_score,
    default_weights,
    flat_fusion,
    minmax_normalise,
    nan_argmax,
    top_k,
    union,
    zscore,
)

NAN = np.nan


# ---------------------------------------------------------------------------------------------
# minmax_normalise
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("faithful", [False, True])
def test_minmax_distance_direction(faithful: bool) -> None:
    # distances [2, 4, 6, 10]: min 2, max 10, range 8; S = (max - x) / range
    #   (10-2)/8 = 1, (10-4)/8 = 0.75, (10-6)/8 = 0.5, (10-10)/8 = 0
    out = minmax_normalise(np.array([2.0, 4.0, 6.0, 10.0]), faithful=faithful)
    np.testing.assert_allclose(out, [1.0, 0.75, 0.5, 0.0], rtol=0, atol=1e-15)
    assert out.dtype == np.float64


@pytest.mark.parametrize("faithful", [False, True])
def test_minmax_similarity_direction(faithful: bool) -> None:
    # similarities [2, 4, 6, 10]: S = (x - min) / range = 0, 2/8, 4/8, 8/8
    out = minmax_normalise(np.array([2, 4, 6, 10]), higher_is_better=True, faithful=faithful)
    np.testing.assert_allclose(out, [0.0, 0.25, 0.5, 1.0], rtol=0, atol=1e-15)
    assert out.dtype == np.float64


def test_minmax_unordered_input_and_no_mutation() -> None:
    # distances [5, 1, 3, 9, 2, 7]: min 1, max 9, range 8; S = (9 - x) / 8
    #   = [4/8, 8/8, 6/8, 0/8, 7/8, 2/8]
    raw = np.array([5.0, 1.0, 3.0, 9.0, 2.0, 7.0])
    out = minmax_normalise(raw)
    np.testing.assert_allclose(out, [0.5, 1.0, 0.75, 0.0, 0.875, 0.25], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(raw, [5.0, 1.0, 3.0, 9.0, 2.0, 7.0])


def test_minmax_constant_faithful_is_all_nan() -> None:
    # MATLAB: (x - max) / (min - max) = 0 / 0 = NaN for every entry.
    out = minmax_normalise(np.array([3.0, 3.0, 3.0]), faithful=True)
    assert out.shape == (3,)
    assert np.isnan(out).all()
    out = minmax_normalise(np.array([3.0, 3.0, 3.0]), higher_is_better=True, faithful=True)
    assert np.isnan(out).all()


def test_minmax_constant_default_is_all_ones() -> None:
    # Default mode: "every entry is equally the best".
    np.testing.assert_array_equal(minmax_normalise(np.array([3.0, 3.0, 3.0])), [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(
        minmax_normalise(np.array([-2.0, -2.0]), higher_is_better=True), [1.0, 1.0]
    )


def test_minmax_single_entry() -> None:
    # One entry is a constant vector.
    np.testing.assert_array_equal(minmax_normalise(np.array([7.0])), [1.0])
    assert np.isnan(minmax_normalise(np.array([7.0]), faithful=True)).all()


@pytest.mark.parametrize("faithful", [False, True])
def test_minmax_nan_entries_ignored(faithful: bool) -> None:
    # finite entries [1, 3, 5]: min 1, max 5, range 4
    # distance: (5-1)/4 = 1, (5-3)/4 = 0.5, (5-5)/4 = 0; NaN stays NaN
    raw = np.array([NAN, 1.0, 3.0, NAN, 5.0])
    np.testing.assert_allclose(
        minmax_normalise(raw, faithful=faithful), [NAN, 1.0, 0.5, NAN, 0.0], rtol=0, atol=1e-15
    )
    # similarity: (1-1)/4 = 0, (3-1)/4 = 0.5, (5-1)/4 = 1
    np.testing.assert_allclose(
        minmax_normalise(raw, True, faithful=faithful),
        [NAN, 0.0, 0.5, NAN, 1.0],
        rtol=0,
        atol=1e-15,
    )


def test_minmax_constant_with_nan() -> None:
    # The finite part [2, 2] is constant: default -> ones on finite entries, NaN kept;
    # faithful -> NaN everywhere.
    raw = np.array([NAN, 2.0, 2.0])
    np.testing.assert_array_equal(minmax_normalise(raw), [NAN, 1.0, 1.0])
    assert np.isnan(minmax_normalise(raw, faithful=True)).all()


@pytest.mark.parametrize("faithful", [False, True])
def test_minmax_all_nan(faithful: bool) -> None:
    out = minmax_normalise(np.array([NAN, NAN]), faithful=faithful)
    assert out.shape == (2,)
    assert np.isnan(out).all()


# ---------------------------------------------------------------------------------------------
# top_k
# ---------------------------------------------------------------------------------------------


def test_top_k_descending_order() -> None:
    # [0.2, 0.9, 0.5, 0.95, 0.1]: highest 0.95 (3), 0.9 (1), 0.5 (2)
    out = top_k(np.array([0.2, 0.9, 0.5, 0.95, 0.1]), 3)
    np.testing.assert_array_equal(out, [3, 1, 2])
    assert out.dtype == np.int64


def test_top_k_ties_lower_index_first() -> None:
    s = np.array([0.5, 0.5, 0.5, 1.0, 0.5])
    # 1.0 at 3 first, then the tied 0.5s in index order 0, 1, 2, 4
    np.testing.assert_array_equal(top_k(s, 1), [3])
    np.testing.assert_array_equal(top_k(s, 2), [3, 0])
    np.testing.assert_array_equal(top_k(s, 3), [3, 0, 1])
    np.testing.assert_array_equal(top_k(s, 5), [3, 0, 1, 2, 4])


def test_top_k_ties_at_the_cut() -> None:
    # [1, 0.5, 0.5, 0.5, 0.5, 0.2], k=3: 0 first, then two of the four tied 0.5s: 1, 2
    np.testing.assert_array_equal(top_k(np.array([1, 0.5, 0.5, 0.5, 0.5, 0.2]), 3), [0, 1, 2])
    # ties straddling the cut in reverse index order of value: [0.5, 0.7, 0.5, 0.7, 0.5], k=3
    #   -> 0.7 at 1, 0.7 at 3, then the first 0.5 at 0
    np.testing.assert_array_equal(top_k(np.array([0.5, 0.7, 0.5, 0.7, 0.5]), 3), [1, 3, 0])


def test_top_k_zeros_tie_by_index() -> None:
    # Faithful zero scatter: off-candidate zeros tie with a real zero score; lowest index wins.
    # [0, 0, 0, 0, 0, 1] (entry 4 is a real candidate scoring 0), k=3 -> [5, 0, 1]
    np.testing.assert_array_equal(top_k(np.array([0, 0, 0, 0, 0, 1.0]), 3), [5, 0, 1])


def test_top_k_nan_skipped() -> None:
    s = np.array([NAN, 0.3, NAN, 0.7, 0.0])
    np.testing.assert_array_equal(top_k(s, 2), [3, 1])
    np.testing.assert_array_equal(top_k(s, 3), [3, 1, 4])


def test_top_k_k_larger_than_valid_entries() -> None:
    # Three non-NaN entries: a list of three, not k.
    s = np.array([NAN, 0.3, NAN, 0.7, 0.0])
    np.testing.assert_array_equal(top_k(s, 10), [3, 1, 4])
    np.testing.assert_array_equal(top_k(np.array([0.1, 0.4]), 5), [1, 0])


def test_top_k_degenerate() -> None:
    assert top_k(np.array([NAN, NAN]), 2).size == 0
    assert top_k(np.array([0.1, 0.2]), 0).size == 0
    assert top_k(np.zeros(0), 3).size == 0


def _matlab_top_k(s: np.ndarray, k: int) -> list[int]:
    """Reference: the original's repeated max-then-NaN-out (first index on ties)."""
    d = s.astype(np.float64).copy()
    out = []
    for _ in range(k):
        j = int(np.nanargmax(d))
        out.append(j)
        d[j] = np.nan
    return out


def test_top_k_matches_repeated_max_on_many_ties() -> None:
    # Values from {0, 0.25, ..., 1} with NaN holes: many ties, exercises the partition path.
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        s = rng.integers(0, 5, n) / 4.0
        s[rng.random(n) < 0.2] = np.nan
        valid = int((~np.isnan(s)).sum())
        for k in range(1, valid + 1):
            np.testing.assert_array_equal(top_k(s, k), _matlab_top_k(s, k))


# ---------------------------------------------------------------------------------------------
# union
# ---------------------------------------------------------------------------------------------


def test_union_faithful_keeps_duplicates_in_concatenation_order() -> None:
    out = union([np.array([3, 1, 4]), np.array([1, 5, 3])], faithful=True)
    np.testing.assert_array_equal(out, [3, 1, 4, 1, 5, 3])
    assert out.dtype == np.int64


def test_union_default_removes_later_repeats() -> None:
    out = union([np.array([3, 1, 4]), np.array([1, 5, 3])])
    np.testing.assert_array_equal(out, [3, 1, 4, 5])
    # repeats inside one list too; first-occurrence order, not sorted
    np.testing.assert_array_equal(union([np.array([9, 2, 9, 0, 2])]), [9, 2, 0])
    np.testing.assert_array_equal(
        union([np.array([9, 2, 9, 0, 2])], faithful=True), [9, 2, 9, 0, 2]
    )


@pytest.mark.parametrize("faithful", [False, True])
def test_union_empty(faithful: bool) -> None:
    assert union([], faithful=faithful).size == 0
    np.testing.assert_array_equal(
        union([np.zeros(0, np.int64), np.array([2])], faithful=faithful), [2]
    )


# ---------------------------------------------------------------------------------------------
# zscore
# ---------------------------------------------------------------------------------------------


def test_zscore_sample_std() -> None:
    # [1, 2, 3]: mean 2, sample var ((1 + 0 + 1) / 2) = 1 -> [-1, 0, 1]
    np.testing.assert_allclose(zscore(np.array([1.0, 2.0, 3.0])), [-1.0, 0.0, 1.0], atol=1e-15)
    # [0, 0, 3]: mean 1, sample var (1 + 1 + 4) / 2 = 3 -> [-1, -1, 2] / sqrt(3)
    r3 = math.sqrt(3.0)
    np.testing.assert_allclose(
        zscore(np.array([0.0, 0.0, 3.0])), [-1 / r3, -1 / r3, 2 / r3], rtol=1e-13
    )
    # [1, 2, 3, 4]: mean 2.5, sample var (2.25 + .25 + .25 + 2.25) / 3 = 5/3
    #   -> [-1.5, -.5, .5, 1.5] / sqrt(5/3) = [-1.161895, -0.387298, 0.387298, 1.161895]
    np.testing.assert_allclose(
        zscore(np.array([1.0, 2.0, 3.0, 4.0])),
        [-1.1618950038622251, -0.3872983346207417, 0.3872983346207417, 1.1618950038622251],
        rtol=1e-13,
    )


def test_zscore_two_entries() -> None:
    # [0, 1]: mean .5, sample var (.25 + .25) / 1 = .5 -> [-.5, .5] / sqrt(.5) = -+1/sqrt(2)
    h = 1 / math.sqrt(2.0)
    np.testing.assert_allclose(zscore(np.array([0.0, 1.0])), [-h, h], rtol=1e-13)


def test_zscore_constant_is_zeros() -> None:
    np.testing.assert_array_equal(zscore(np.array([1.75, 1.75, 1.75])), [0.0, 0.0, 0.0])


def test_zscore_single_entry_is_zero() -> None:
    np.testing.assert_array_equal(zscore(np.array([4.2])), [0.0])


def test_zscore_any_nan_is_all_nan() -> None:
    out = zscore(np.array([1.0, NAN, 3.0]))
    assert out.shape == (3,)
    assert np.isnan(out).all()


def test_zscore_empty() -> None:
    assert zscore(np.zeros(0)).shape == (0,)


# ---------------------------------------------------------------------------------------------
# nan_argmax
# ---------------------------------------------------------------------------------------------


def test_nan_argmax() -> None:
    assert nan_argmax(np.array([0.1, 0.7, 0.7, 0.2])) == 1  # first maximum
    assert nan_argmax(np.array([NAN, 0.2, NAN, 0.5])) == 3  # NaN skipped
    assert nan_argmax(np.array([-1.0, NAN, -0.5])) == 2
    assert nan_argmax(np.array([NAN, NAN, NAN])) == 0  # MATLAB max of all NaN -> index 1
    assert nan_argmax(np.zeros(0)) == 0
    assert isinstance(nan_argmax(np.array([0.0, 1.0])), int)


# ---------------------------------------------------------------------------------------------
# combined_score
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("faithful", [False, True])
def test_combined_score_two_tiers(faithful: bool) -> None:
    # 3 final candidates, weights (0.75, 1.0).
    # tier 1 values [1.0, 0.8, 0.9]: min .8, max 1, range .2
    #   -> [(1-.8)/.2, 0, (.9-.8)/.2] = [1, 0, .5] * .75 = [.75, 0, .375]
    # tier 2 values [0.2, 1.0, 0.6]: min .2, max 1, range .8
    #   -> [0, 1, .5] * 1 = [0, 1, .5]
    # Dsuper = [.75, 1.0, .875]
    x1 = np.array([1.0, 0.8, 0.9])
    x2 = np.array([0.2, 1.0, 0.6])
    d = combined_score([x1, x2], (0.75, 1.0), faithful=faithful)
    np.testing.assert_allclose(d, [0.75, 1.0, 0.875], rtol=1e-13)
    # zscore: mean .875, deviations [-.125, .125, 0], sample var .03125/2 = .015625,
    # sd .125 -> [-1, 1, 0]
    np.testing.assert_allclose(zscore(d), [-1.0, 1.0, 0.0], atol=1e-12)


def test_combined_score_three_tiers_default_weights() -> None:
    # weights (.5, .75, 1), 4 candidates
    # t1 [.5, 1, .75, .5]    -> min .5 range .5 -> [0, 1, .5, 0]   * .5  = [0, .5, .25, 0]
    # t2 [0, .2, .4, .8]     -> min 0 range .8  -> [0, .25, .5, 1] * .75 = [0, .1875, .375, .75]
    # t3 [3, 1, 2, 5]        -> min 1 range 4   -> [.5, 0, .25, 1] * 1   = [.5, 0, .25, 1]
    # Dsuper = [.5, .6875, .875, 1.75]
    d = combined_score(
        [np.array([0.5, 1, 0.75, 0.5]), np.array([0, 0.2, 0.4, 0.8]), np.array([3.0, 1, 2, 5])],
        DEFAULT_WEIGHTS,
    )
    np.testing.assert_allclose(d, [0.5, 0.6875, 0.875, 1.75], rtol=1e-13)


def test_combined_score_constant_tier() -> None:
    # tier 1 values constant [.5, .5, .5]:
    #   faithful: 0/0 -> NaN for every entry, so Dsuper is all NaN (and so is its zscore)
    #   default: ones * .75 = .75 everywhere, tier 2 [0, 1, .5] added -> [.75, 1.75, 1.25]
    x1 = np.array([0.5, 0.5, 0.5])
    x2 = np.array([0.2, 1.0, 0.6])
    d = combined_score([x1, x2], (0.75, 1.0), faithful=True)
    assert np.isnan(d).all()
    assert np.isnan(zscore(d)).all()
    np.testing.assert_allclose(
        combined_score([x1, x2], (0.75, 1.0)), [0.75, 1.75, 1.25], rtol=1e-13
    )


def test_combined_score_single_candidate() -> None:
    # F of length 1: each tier is a constant vector.
    # faithful: NaN; default: 1 * w summed = .75 + 1 = 1.75
    assert np.isnan(
        combined_score([np.array([1.0]), np.array([0.3])], (0.75, 1.0), faithful=True)
    ).all()
    np.testing.assert_allclose(
        combined_score([np.array([1.0]), np.array([0.3])], (0.75, 1.0)), [1.75]
    )


def test_combined_score_weight_count_must_match() -> None:
    with pytest.raises(ValueError):
        combined_score([np.array([1.0, 0.0])], (0.75, 1.0))


# ---------------------------------------------------------------------------------------------
# flat_fusion
# ---------------------------------------------------------------------------------------------


def test_flat_fusion_mixed_directions() -> None:
    # method A distances [1, 3, 5]: (5 - x)/4 = [1, .5, 0]
    # method B similarities [0, 10, 5]: x/10 = [0, 1, .5]
    # mean = [.5, .75, .25]
    out = flat_fusion([np.array([1.0, 3.0, 5.0]), np.array([0.0, 10.0, 5.0])], [False, True])
    np.testing.assert_allclose(out, [0.5, 0.75, 0.25], rtol=1e-13)


def test_flat_fusion_constant_method() -> None:
    # B constant: faithful -> NaN, so the mean is NaN everywhere;
    # default -> ones, mean with A [1, .5, 0] = [1, .75, .5]
    a = np.array([1.0, 3.0, 5.0])
    b = np.array([2.0, 2.0, 2.0])
    assert np.isnan(flat_fusion([a, b], [False, False], faithful=True)).all()
    np.testing.assert_allclose(flat_fusion([a, b], [False, False]), [1.0, 0.75, 0.5], rtol=1e-13)


def test_flat_fusion_single_method_is_its_normalisation() -> None:
    # distances [5, 1, 3, 9, 2, 7] -> (9 - x)/8
    np.testing.assert_allclose(
        flat_fusion([np.array([5.0, 1, 3, 9, 2, 7])], [False]),
        [0.5, 1.0, 0.75, 0.0, 0.875, 0.25],
        rtol=1e-13,
    )


def test_flat_fusion_direction_count_must_match() -> None:
    with pytest.raises(ValueError):
        flat_fusion([np.array([1.0, 2.0]), np.array([2.0, 1.0])], [False])


# ---------------------------------------------------------------------------------------------
# default_weights
# ---------------------------------------------------------------------------------------------


def test_default_weights() -> None:
    assert DEFAULT_WEIGHTS == (0.5, 0.75, 1.0)
    assert default_weights(1) == (1.0,)
    assert default_weights(2) == (0.75, 1.0)
    assert default_weights(3) == (0.5, 0.75, 1.0)
    with pytest.raises(ValueError):
        default_weights(4)
