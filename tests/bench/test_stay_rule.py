"""bench/stay_rule.py's pieces: the drives that leave the map and come back, the tally of a
policy's decisions on them, and the choice of the floor."""

from __future__ import annotations

import numpy as np

from bench import stay_rule as sr
from hmpf.evaluation.sequence import Drive


def test_spliced_inserts_a_block_of_away_frames_before_each_mark() -> None:
    inside = np.arange(10)
    away = np.arange(100, 120)
    frames, flag = sr.spliced(inside, away, [3, 7], start=18)
    b = sr.BLOCK
    assert len(frames) == 10 + 2 * b and flag.sum() == 2 * b
    # every in-map frame once, in order; the blocks before steps 3 and 7
    assert frames[~flag].tolist() == inside.tolist()
    assert frames[3 : 3 + b].tolist() == [100 + (18 + j) % 20 for j in range(b)]
    assert frames[3 + b] == 3 and frames[6 + b] == 6 and frames[7 + b + b] == 7
    assert flag[3 : 3 + b].all() and not flag[:3].any()
    # no away frames: the drive as it was
    frames, flag = sr.spliced(inside, np.zeros(0, np.int64), [3])
    assert frames.tolist() == inside.tolist() and not flag.any()


def test_leave_drives_leave_each_drive_at_its_marks_with_fresh_blocks() -> None:
    drives = [Drive.along(np.arange(20)), Drive.along(np.arange(0, 20, 2))]
    away = np.arange(200, 300)
    out, flags = sr.leave_drives(drives, away)
    assert len(flags) == sum(len(d.frames) for d in out)
    assert len(out[0].frames) == 20 + len(sr.LEAVES) * sr.BLOCK
    used = np.concatenate([d.frames for d in out])[flags]
    assert len(set(used.tolist())) == len(used)  # consecutive blocks, none reused here
    assert all((d.steps == 1).all() for d in out)


def test_tally_counts_first_frames_of_leaves_per_drive_and_flips_in_the_map() -> None:
    #          drive 0                  | drive 1
    away = np.array([0, 0, 1, 1, 0, 0,    1, 0, 0, 1], bool)  # fmt: skip
    acc = np.array([1, 1, 1, 0, 0, 1,     1, 1, 0, 0], bool)  # fmt: skip
    right = np.array([1, 1, 0, 0, 1, 0,   0, 1, 1, 0], bool)  # fmt: skip
    drive = np.array([0] * 6 + [1] * 4)
    got = sr.tally(acc, away, right, drive)
    assert got["away"] == 4 and got["away_accepted"] == 2
    # leaves: step 2 (drive 0), step 6 (drive 1's first step, away), step 9
    assert got["leaves"] == 3 and got["first_away_accepted"] == 2
    assert got["in_map"] == 6 and got["in_map_accepted"] == 4 / 6
    assert got["precision"] == 3 / 4
    # in the map, drive 0: 1 1 0 1 -> 2 flips; drive 1: 1 0 -> 1 flip
    assert got["flips_per_100"] == 100 * 3 / 6


def test_choose_takes_the_least_strict_floor_that_adds_no_away_frame() -> None:
    rows = [
        {"floor": None, "away_accepted": 9},
        {"floor": -2.0, "away_accepted": 4},
        {"floor": -1.0, "away_accepted": 1},
        {"floor": -0.5, "away_accepted": 1},
        {"floor": 0.0, "away_accepted": 0},
    ]
    assert sr.choose(rows, entry_away=1) == -1.0
    assert sr.choose(rows, entry_away=0) == 0.0
    assert sr.choose(rows[:3], entry_away=0) is None
    assert sr.choose([{"floor": None, "away_accepted": 0}], entry_away=0) is None
