"""Sequence mode of the evaluation: drives, frames to lock, the report and the tuning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hmpf.confidence import ReferenceProfile
from hmpf.evaluation.sequence import (
    Drive,
    dropped_drive,
    evidences_of,
    jump_drives,
    leave_drives,
    lock_frames,
    lock_threshold,
    off_map_report,
    sequence_report,
    sequence_settings,
    speed_drive,
    start_drives,
    tune_sequence,
)
from hmpf.hierarchy import HierarchyResult, TierResult
from hmpf.sequence import FilterParams, RouteMap


def _results(n: int, rng: np.random.Generator, wrong: float = 0.35) -> list[HierarchyResult]:
    """Query i shows reference i; a share of the frames point at a random wrong place."""
    out = []
    for i in range(n):
        score = rng.random(n) * 0.6
        peak = int(rng.integers(n)) if rng.random() < wrong else i
        score[max(0, peak - 1) : peak + 2] += 0.3
        score[peak] = 1.0
        final = np.argsort(-score)[:5]
        z = np.linspace(2.0, -0.5, 5)
        tier = TierResult(["m"], None, {"m": score}, final, 0.0)
        out.append(HierarchyResult(int(final[0]), float(z[0]), final, z, [tier]))
    return out


def test_lock_frames_counts_from_the_start_and_needs_a_run_of_right_answers():
    c = np.array([0, 1, 0, 1, 1, 1, 1, 1, 0, 1], dtype=bool)
    assert lock_frames(c, hold=5) == 4  # frames 4-8 (1-based) are right
    assert lock_frames(c, start=8, hold=5) == 2  # frame 10 right to the end counts
    assert lock_frames(np.zeros(6, bool)) is None
    assert lock_frames(np.ones(3, bool), hold=5) == 1


def test_drives_speed_jump_dropped_and_starts():
    rng = np.random.default_rng(0)
    assert speed_drive(10, 2.0, 1).frames.tolist() == [1, 3, 5, 7, 9]
    assert speed_drive(3, 0.5).frames.tolist() == [0, 0, 1, 1, 2, 2]
    for d in jump_drives(100, 30, 20, 30, 25, rng):
        a, b = d.frames[0], d.frames[d.splice]
        assert d.splice == 20 and len(d.frames) == 50
        assert abs(int(b) - int(a)) >= 25 and abs(int(b) - int(d.frames[19]) - 1) >= 24
        assert np.diff(d.frames[:20]).tolist() == [1] * 19
    d = dropped_drive(200, 0.25, rng)
    assert d.steps.sum() == d.frames[-1] + 1  # every gap told to the filter
    assert 0.6 < len(d.frames) / 200 < 0.9 and (d.steps >= 1).all()
    starts = start_drives(100, 10, 20, 3.0, rng)
    assert len(starts) == 10 and all(len(s.frames) == 20 for s in starts)
    assert all(np.diff(s.frames).tolist() == [3] * 19 for s in starts)


def test_sequence_report_beats_single_frames_and_counts_every_frame():
    rng = np.random.default_rng(1)
    n = 120
    results = _results(n, rng)
    gt = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= 2
    rep = sequence_report(results, gt, RouteMap.from_metadata(n), FilterParams(), starts=20)
    assert len(rep["full_drive"]["correct"]) == n  # the first frames count
    assert rep["single_recall_at_1"] < 0.75
    assert rep["recall_at_1"] > rep["single_recall_at_1"] + 0.15
    assert set(rep["recall_by_speed"]) == {"0.5", "1", "2", "3", "4"}
    assert all(0 <= v <= 1 for v in rep["recall_by_speed"].values())
    curve = rep["recall_by_history"]["1"]
    assert len(curve) == 20 and np.mean(curve[-5:]) >= np.mean(curve[:2])  # history helps
    acc = rep["accepted"]
    assert 0 <= acc["recall"] <= acc["accepted"] <= 1
    assert rep["lock_after_jump"]["n"] > 50
    assert rep["lock_after_jump"]["median"] <= 10


def test_tuning_picks_a_grid_point_and_a_lock_threshold_for_the_precision():
    rng = np.random.default_rng(2)
    n = 80
    results = _results(n, rng)
    gt = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= 2
    grid = {"evidence_weight": (0.1, 0.5), "jump": (0.01, 0.05)}
    params, info = tune_sequence(
        [(results, gt, RouteMap.from_metadata(n))], grid=grid, target_precision=0.95
    )
    assert len(info["grid"]) == 4
    best = max(info["grid"], key=lambda r: r["score"])
    assert (params.evidence_weight, params.jump) == (best["evidence_weight"], best["jump"])
    assert params.lock_mass == pytest.approx(max(info["lock_mass"], 1e-6))
    assert set(sequence_settings(params)) <= {"evidence_weight", "jump", "lock_mass"}
    assert sequence_settings(FilterParams()) == {}


def test_lock_threshold_hand_computed():
    mass = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
    correct = np.array([1, 1, 0, 1, 1], dtype=bool)
    assert lock_threshold(mass, correct, 1.0) == 0.8
    assert lock_threshold(mass, correct, 0.8) == 0.5  # 4 of 5 right
    assert lock_threshold(mass, np.zeros(5, bool), 0.9) == 1.0  # unreachable: nothing


def test_drive_dataclass_defaults():
    d = Drive.along([3, 4, 5])
    assert d.steps.tolist() == [1, 1, 1] and d.splice is None


def _raw_results(n: int, m: int, rng: np.random.Generator) -> list[HierarchyResult]:
    """``n`` in-map queries (query i shows reference i, raw score 1 there) then ``m`` frames
    from elsewhere (raw scores of clutter, its best reference random), over ``n``
    references."""
    out = []
    for i in range(n + m):
        raw = rng.uniform(0.0, 0.5, n)
        peak = i if i < n else int(np.argmax(raw))
        if i < n:
            raw[max(0, i - 1) : i + 2] += 0.3
            raw[i] = 1.0
        score = raw / raw.max()
        final = np.argsort(-score)[:5]
        tier = TierResult(["m"], None, {"m": score}, final, 0.0, {"m": raw})
        out.append(HierarchyResult(peak, 2.0, final, np.linspace(2.0, -0.5, 5), [tier]))
    return out


def test_evidences_of_reads_the_absolute_evidence_with_a_profile():
    rng = np.random.default_rng(3)
    results = _raw_results(40, 5, rng)
    profile = ReferenceProfile(("m",), (1.0,), np.full((1, 40), 0.25), np.full((1, 40), 0.15))
    evs = evidences_of(results, 40, 10, profile)
    for r, e in zip(results, evs, strict=True):
        raw = r.tiers[0].raw["m"][r.match]
        assert e.absolute == pytest.approx((raw - 0.25) / 0.15)
    assert min(e.absolute for e in evs[:40]) == pytest.approx(0.75 / 0.15)
    assert max(e.absolute for e in evs[40:]) < 0.25 / 0.15
    assert all(np.isnan(e.absolute) for e in evidences_of(results, 40, 10))


def test_leave_drives_and_the_off_map_report():
    rng = np.random.default_rng(4)
    for d in leave_drives(100, 60, 20, 10, 15, 20, rng):
        assert d.away == (10, 25) and d.splice == 25 and len(d.frames) == 45
        assert (d.frames[10:25] >= 100).all() and (d.frames[:10] < 100).all()
        assert np.diff(d.frames[10:25]).tolist() == [1] * 14 and d.frames[25] >= d.frames[9] + 1
    assert leave_drives(10, 60, 5, 10, 15, 20, rng) == []  # the route is too short
    n, m = 120, 60
    results = _raw_results(n, m, np.random.default_rng(5))
    gt = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= 2
    profile = ReferenceProfile(("m",), (1.0,), np.full((1, n), 0.25), np.full((1, n), 0.15))
    params = FilterParams(off_center=3.0, off_slope=1.0)
    rep = off_map_report(results[:n], results[n:], gt, RouteMap.from_metadata(n), params, profile)
    w, wo = rep["with_off"], rep["without_off"]
    assert rep["n_drives"] == 40 and rep["absolute"]["away"]["p95"] < 3.0
    assert w["away_off_map"] > 0.8 and wo["away_off_map"] == 0.0
    assert w["on_map_off_map"] < 0.1 and w["away_accepted"] <= wo["away_accepted"]
    assert w["frames_back_on_map"]["median"] <= 2 and w["frames_to_relock"]["median"] <= 10


def test_hmpf_eval_sequence_with_foreign_frames_drives_off_the_map_and_back(
    gardens_point: Path, nordland: Path, tmp_path: Path, capsys
) -> None:
    """``hmpf-eval --sequence --foreign DIR``: real frames (Gardens Point day_left ->
    day_right, 60 each; 40 Nordland winter thumbnails as the place off the map), the
    default preset (whose tier-1 evidence the off state's likelihood was set on; with a
    handcrafted tier 1 these frames score -0.2 to -0.3 against unrelated references, near
    ``off_center``, and are not put off the map): the report says how the drives that
    leave and come back went, and the off state is what puts the frames away off the map
    (without it, none is)."""
    import json
    import shutil

    from hmpf.cli.eval import main as eval_main

    folders = {}
    for name, src, n in (
        ("refs", gardens_point / "day_left", 60),
        ("qrys", gardens_point / "day_right", 60),
        ("away", nordland / "winter", 40),
    ):
        folders[name] = tmp_path / name
        folders[name].mkdir()
        frames = sorted(src.iterdir())
        for p in frames[:n] if name != "away" else frames[1000 : 1000 + n]:
            shutil.copy(p, folders[name] / p.name)
    out = tmp_path / "r.json"
    args = ["--config", "default", "--reference", str(folders["refs"])]
    args += ["--query", str(folders["qrys"]), "--tolerance", "2", "--no-cache", "--quiet"]
    args += ["--workers", "1", "--sequence", "--foreign", str(folders["away"])]
    assert eval_main([*args, "--json", str(out)]) == 0
    assert "leaving the map and coming back" in capsys.readouterr().out
    full = json.loads(out.read_text())
    # the default preset's models read the map's prior: hmpf-eval computes it for these
    # references, as hmpf-index build stores it
    assert full["map_prior"]["pseudo_queries"] > 0
    assert -10 < full["map_prior"]["map_prior"] < 10
    rep = full["off_map"]
    with_off, without = rep["with_off"], rep["without_off"]
    assert rep["n_drives"] > 0
    assert with_off["away_off_map"] > 0.5 and without["away_off_map"] == 0.0
    assert with_off["away_accepted"] <= without["away_accepted"]
    with pytest.raises(SystemExit):  # --foreign needs --sequence
        eval_main([a for a in args if a != "--sequence"])
