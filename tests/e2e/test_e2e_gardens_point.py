"""End to end on real data: ``hmpf-eval`` as a user runs it, on Gardens Point.

Recall floors sit a few points under the measured values (README, "Results") so a regression
in any method, the fusion or the evaluation fails the suite.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _eval(args: list[str], cache: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hmpf.cli.eval", "--quiet", "--cache-dir", str(cache), *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=900,
    )


@pytest.mark.dataset
@pytest.mark.slow  # minutes on 2 cores (whole Gardens Point protocols)
def test_handcrafted_day_right_to_night_right(
    gardens_point: Path, gp_feature_cache: Path, tmp_path: Path
):
    out = tmp_path / "report.json"
    cache = gp_feature_cache  # shared: what an earlier test extracted is read, not redone
    args = [
        "--config",
        "configs/handcrafted.yaml",
        "--reference",
        str(gardens_point / "day_right"),
        "--query",
        str(gardens_point / "night_right"),
        "--tolerance",
        "2",
        "--json",
        str(out),
    ]
    proc = _eval(args, cache)
    assert proc.returncode == 0, proc.stderr
    assert "Combined recall@1" in proc.stdout
    rep = json.loads(out.read_text())
    m = rep["methods"]
    assert set(m) == {"hog", "gist", "sad", "kaze"}
    for name in m:
        assert set(m[name]["recall_at"]) == {"1", "5", "10", "20", "50", "100"}
        r = [m[name]["recall_at"][k] for k in ("1", "5", "10", "20", "50", "100")]
        assert r == sorted(r)  # recall@N never decreases with N
    assert m["hog"]["recall_at"]["1"] >= 0.45
    assert m["gist"]["recall_at"]["1"] >= 0.55
    assert m["kaze"]["recall_at"]["1"] >= 0.22
    assert m["sad"]["recall_at"]["1"] >= 0.18
    h = rep["hierarchy"]
    assert h["combined_recall_at_1"] >= 0.62
    assert h["flat_recall_at_1"] >= 0.57
    assert h["tiers"][0]["recall"] >= 0.95
    assert h["tiers"][0]["recall"] >= h["tiers"][1]["recall"] >= h["tiers"][2]["recall"]
    # The hierarchy beats its best single method on this protocol.
    assert h["combined_recall_at_1"] > max(m[n]["recall_at"]["1"] for n in m)
    assert 0.0 < h["pr"]["auc"] <= 1.0
    assert len(rep["timing_ms"]["tiers_per_query"]) == 3

    # Second run: every descriptor comes from the cache (whatever the first run found
    # there, it stored the rest), results are identical.
    out2 = tmp_path / "report2.json"
    proc = _eval([*args[:-1], str(out2), "--skip-curves", "kaze", "--sequence"], cache)
    assert proc.returncode == 0, proc.stderr
    rep2 = json.loads(out2.read_text())
    # --sequence: the night traverse driven as one vehicle, every frame counted.
    seq = rep2["sequence"]
    assert "sequence mode" in proc.stdout and len(seq["full_drive"]["correct"]) == 200
    assert seq["single_recall_at_1"] == h["combined_recall_at_1"]
    assert seq["recall_at_1"] >= h["combined_recall_at_1"] + 0.15
    assert seq["lock_after_jump"]["n"] >= 50 and seq["lock_after_start"]["n"] >= 20
    assert rep2["cache"]["reference_cached"] == {k: 200 for k in m}
    assert rep2["cache"]["query_cached"] == {k: 200 for k in m}
    assert rep2["hierarchy"]["matches"] == h["matches"]
    assert "recall_at" not in rep2["methods"]["kaze"]


def test_cli_reports_bad_config_without_traceback(tmp_path: Path, image_folder):
    folder = image_folder("imgs", 2)
    bad = tmp_path / "bad.yaml"
    bad.write_text("tiers: [{methods: [hog], k: 1}]\nweight: [1]\n")
    proc = _eval(
        ["--config", str(bad), "--reference", str(folder), "--query", str(folder)],
        tmp_path / "cache",
    )
    assert proc.returncode == 2
    assert "unknown key 'weight'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_reports_empty_folder(tmp_path: Path):
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = _eval(
        ["--config", "configs/handcrafted.yaml", "--reference", str(empty), "--query", str(empty)],
        tmp_path / "cache",
    )
    assert proc.returncode == 2
    assert "holds no image" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.dataset
@pytest.mark.slow  # minutes on 2 cores (whole Gardens Point protocols)
def test_default_hierarchy_beats_best_single_and_flat(
    gardens_point: Path, gp_feature_cache: Path, tmp_path: Path
):
    """configs/default.yaml on the two night protocols (issue: must beat its best single
    method and flat fusion of the same methods on both)."""
    cache = gp_feature_cache
    for ref in ("day_right", "day_left"):
        out = tmp_path / f"{ref}.json"
        proc = _eval(
            [
                "--config",
                "configs/default.yaml",
                "--reference",
                str(gardens_point / ref),
                "--query",
                str(gardens_point / "night_right"),
                "--tolerance",
                "2",
                "--json",
                str(out),
            ],
            cache,
        )
        assert proc.returncode == 0, proc.stderr
        rep = json.loads(out.read_text())
        m, h = rep["methods"], rep["hierarchy"]
        best = max(m[n]["recall_at"]["1"] for n in m)
        assert h["combined_recall_at_1"] > best, (ref, h["combined_recall_at_1"], best)
        assert h["combined_recall_at_1"] > h["flat_recall_at_1"], ref
        floor = {"day_right": 0.78, "day_left": 0.58}[ref]
        assert h["combined_recall_at_1"] >= floor, (ref, h["combined_recall_at_1"])
        assert sorted(rep["fitted_methods"]) == ["netvlad", "olo"]
