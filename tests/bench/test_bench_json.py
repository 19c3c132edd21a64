"""The ``--json`` records of bench/index_search.py, bench/sequence_scale.py and
bench/profile_scale.py: real runs at tiny sizes (seconds each, in a subprocess: the benches set
their process's thread counts), checked for the keys a page generator reads and for plausible
numbers (positive times, recall within [0, 1], one entry per size)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
PROVENANCE = {"date", "machine", "commit", "arguments"}


def run_bench(module: str, tmp_path: Path, *args: str) -> dict[str, Any]:
    out = tmp_path / f"{module}.json"
    proc = subprocess.run(
        [sys.executable, "-m", f"bench.{module}", *args, "--json", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "report: " in proc.stdout  # the printed table stays, the record is named after it
    data = json.loads(out.read_text())
    assert PROVENANCE <= set(data)
    assert data["arguments"]["json"] == str(out)
    return data


def positive(*values: Any) -> bool:
    return all(isinstance(v, int | float) and v > 0 for v in values)


def test_index_search_json(tmp_path: Path) -> None:
    pytest.importorskip("faiss")
    d = run_bench("index_search", tmp_path, "--sizes", "2000", "3000", "--queries", "20")
    assert isinstance(d["faiss"], str) and d["faiss"]
    assert d["threads"] >= 1 and (d["dim"], d["k"], d["queries"]) == (512, 100, 20)
    assert d["target"] == 0.95
    assert [s["n"] for s in d["sizes"]] == [2000, 3000]
    for s in d["sizes"]:
        assert set(s) == {"n", "flat", "ivf", "rescore_ms"}
        flat, ivf = s["flat"], s["ivf"]
        assert set(flat) == {"build_s", "p50_ms", "p95_ms", "bytes_per_ref"}
        assert set(ivf) == {"factory", "nlist", "nprobe", "build_s", "p50_ms", "p95_ms", "recall"}
        assert positive(flat["build_s"], flat["p50_ms"], flat["p95_ms"], s["rescore_ms"])
        assert positive(ivf["build_s"], ivf["p50_ms"], ivf["p95_ms"])
        assert flat["p50_ms"] <= flat["p95_ms"] and ivf["p50_ms"] <= ivf["p95_ms"]
        assert flat["bytes_per_ref"] == 4 * 512
        assert ivf["factory"] == f"IVF{ivf['nlist']},Flat"
        assert ivf["nprobe"] in (4, 8, 16, 32, 64, 128)
        assert 0.0 <= ivf["recall"] <= 1.0


def test_sequence_scale_json(tmp_path: Path) -> None:
    d = run_bench("sequence_scale", tmp_path, "--sizes", "2000,3000", "--frames", "30")
    assert d["frames"] == 30
    assert d["load_before"] >= 0 and d["load_after"] >= 0
    assert [s["n"] for s in d["sizes"]] == [2000, 3000]
    columns = {
        "n",
        "update_wall_p50_ms",
        "update_wall_p95_ms",
        "update_cpu_p50_ms",
        "update_cpu_p95_ms",
        "keys_weighed_mean",
        "evidence_p50_ms",
        "evidence_p95_ms",
        "route_map_build_s",
        "route_map_mb",
        "build_peak_alloc_mb",
        "junction_entries",
        "drive_accuracy",
    }
    for s in d["sizes"]:
        assert set(s) == columns
        assert positive(
            s["update_wall_p50_ms"],
            s["update_wall_p95_ms"],
            s["evidence_p50_ms"],
            s["evidence_p95_ms"],
            s["route_map_build_s"],
            s["route_map_mb"],
            s["build_peak_alloc_mb"],
            s["keys_weighed_mean"],
        )
        assert 0 <= s["update_cpu_p50_ms"] <= s["update_cpu_p95_ms"]
        assert s["update_wall_p50_ms"] <= s["update_wall_p95_ms"]
        assert isinstance(s["junction_entries"], int) and s["junction_entries"] >= 0
        assert 0.0 <= s["drive_accuracy"] <= 1.0


def test_profile_scale_json(tmp_path: Path) -> None:
    d = run_bench("profile_scale", tmp_path, "--sizes", "2000,3000", "--dim", "64", "--repeat", "1")
    assert (d["dim"], d["threads"], d["repeat"]) == (64, 2, 1)
    assert [s["n"] for s in d["sizes"]] == [2000, 3000]
    for s in d["sizes"]:
        assert set(s) == {
            "n",
            "build_s",
            "build_s_per_million_refs",
            "write_ms",
            "read_ms",
            "sha256_ms",
            "file_bytes",
        }
        assert positive(s["build_s"], s["write_ms"], s["read_ms"], s["sha256_ms"])
        assert s["build_s_per_million_refs"] == pytest.approx(s["build_s"] / s["n"] * 1e6)
        assert isinstance(s["file_bytes"], int) and s["file_bytes"] >= 2 * 8 * s["n"]
