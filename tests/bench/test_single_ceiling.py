"""bench/single_ceiling.py's ceiling: the largest share a threshold accepts at a precision,
checked against brute force over every threshold, ties and NaN scores included; and the
inliers of a real image pair."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench import single_ceiling as sc
from hmpf.datasets import list_images


def brute(score: np.ndarray, correct: np.ndarray, target: float) -> float:
    """Every finite score tried as the threshold (accept ``score >= t``)."""
    best = 0.0
    for t in np.unique(score[~np.isnan(score)]):
        acc = score >= t
        if correct[acc].mean() >= target:
            best = max(best, acc.sum() / len(score))
    return best


@pytest.mark.parametrize("seed", range(40))
def test_ceiling_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    # few distinct values: many ties; some NaN
    score = rng.integers(0, 8, n).astype(np.float64)
    score[rng.random(n) < 0.1] = np.nan
    correct = rng.random(n) < rng.uniform(0.3, 1.0)
    target = float(rng.choice([0.5, 0.8, 0.99]))
    share, thr = sc.ceiling(score, correct, target)
    assert share == pytest.approx(brute(score, correct, target))
    if share:
        acc = score >= thr
        assert acc.sum() / n == pytest.approx(share)
        assert correct[acc].mean() >= target
    else:
        assert thr is None


def test_ceiling_of_a_clean_ordering_and_a_tie_across_the_cut() -> None:
    score = np.array([0.9, 0.8, 0.7, 0.6])
    assert sc.ceiling(score, np.array([True, True, False, True]), 0.99) == (0.5, 0.8)
    # the wrong answer ties with a right one: no threshold separates them
    tied = np.array([0.9, 0.8, 0.8, 0.6])
    assert sc.ceiling(tied, np.array([True, True, False, True]), 0.99) == (0.25, 0.9)
    assert sc.ceiling(tied, np.array([False, True, True, True]), 0.99) == (0.0, None)
    assert sc.ceiling(np.array([np.nan]), np.array([True]), 0.99) == (0.0, None)
    with pytest.raises(ValueError):
        sc.ceiling(score, np.array([True]), 0.99)


def test_verifier_counts_more_inliers_for_the_same_place(gardens_point: Path) -> None:
    """A day frame against itself and against a frame far along the route (real images)."""
    frames = list_images(gardens_point / "day_left")
    v = sc.Verifier()
    a, far = str(frames[0]), str(frames[len(frames) // 2])
    same = v.inliers(a, a)
    assert same > v.inliers(a, far)
    assert len(v._features) == 2  # each image extracted once
