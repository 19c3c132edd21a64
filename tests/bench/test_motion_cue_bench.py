"""bench/motion_cue.py's choice: the grid's best training score wins, a tie goes to the
preset (no cue), and the comparison pairs the two settings frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from bench import motion_cue
from hmpf.sequence import FilterParams


class FakePart:
    """A traverse whose recall per setting is given: ``table[(stop_factor, moved, ratio)]``
    frames right out of 10 (the rest wrong), the preset's (stop_factor 1) whatever moved."""

    def __init__(self, right: dict[tuple[float, float, float], int]) -> None:
        self.right = right

    def correct(self, params: FilterParams, ratio: float) -> np.ndarray:
        key = (params.stop_factor, 0.0 if params.stop_factor == 1.0 else params.moved, ratio)
        n = self.right.get(key, 5)
        return np.arange(10) < n

    def locked(self, params: FilterParams) -> dict[str, float]:
        return {"share": 0.5, "precision": 1.0}


def test_the_best_training_score_is_chosen():
    part = FakePart({(0.1, 0.5, 1.0): 9, (0.1, 0.5, 0.5): 8})
    chosen, rows = motion_cue.choose({"a": part}, FilterParams())
    assert (chosen.stop_factor, chosen.moved) == (0.1, 0.5)
    n_grid = len(motion_cue.GRID["stop_factor"]) * len(motion_cue.GRID["moved"])
    assert len(rows) == n_grid
    best = next(r for r in rows if (r["stop_factor"], r["moved"]) == (0.1, 0.5))
    assert best["score"] == pytest.approx((0.9 + 0.8) / 2)


def test_a_tie_keeps_the_preset():
    chosen, _ = motion_cue.choose({"a": FakePart({})}, FilterParams())
    assert chosen.stop_factor == 1.0 and not chosen.motion


def test_compare_pairs_the_settings_per_speed():
    part = FakePart({(0.1, 0.3, 1.0): 8, (1.0, 0.0, 1.0): 6})
    out = motion_cue.compare(part, FilterParams(stop_factor=0.1, moved=0.3), FilterParams())
    x1 = out["1"]
    assert (x1["cue"], x1["preset"], x1["wins"], x1["losses"]) == (0.8, 0.6, 2, 0)
    assert out["0.5"]["wins"] == out["0.5"]["losses"] == 0
    assert set(out) == {"1", "0.5", "2", "locked"}


class WeightPart:
    """A traverse for the evidence grid: recall out of 10 per ``combined_weight``, and the
    share of jumps re-locked per ``combined_weight`` (default 5 / 0.5)."""

    def __init__(self, right: dict[float, int], relock: dict[float, float]) -> None:
        self.right, self.relock = right, relock

    def correct(self, params: FilterParams, ratio: float) -> np.ndarray:
        return np.arange(10) < self.right.get(params.combined_weight, 5)

    def relocked(self, params: FilterParams) -> float:
        return self.relock.get(params.combined_weight, 0.5)


def test_the_evidence_grid_weighs_relocking_like_a_speed():
    grid = motion_cue.EVIDENCE_GRID
    preset = FilterParams()
    # 0.5 wins the drives (9 of 10) but re-locks no jump: 1.0 (8 of 10, every jump) wins
    part = WeightPart({0.5: 9, 1.0: 8}, {0.5: 0.0, 1.0: 1.0})
    chosen, rows = motion_cue.choose({"a": part}, preset, grid, relock=True)
    assert chosen.combined_weight == 1.0
    row = next(r for r in rows if r["combined_weight"] == 1.0 and r["evidence_weight"] == 0.25)
    assert row["recall"]["a"]["relock"] == 1.0
    assert row["score"] == pytest.approx((0.8 + 0.8 + 1.0) / 3)
    # without the re-lock term the drives alone decide
    chosen, _ = motion_cue.choose({"a": part}, preset, grid)
    assert chosen.combined_weight == 0.5


def test_an_evidence_grid_tie_keeps_the_presets_weights():
    preset = FilterParams()
    chosen, _ = motion_cue.choose({"a": WeightPart({}, {})}, preset, motion_cue.EVIDENCE_GRID, True)
    assert (chosen.combined_weight, chosen.evidence_weight) == (
        preset.combined_weight,
        preset.evidence_weight,
    )
