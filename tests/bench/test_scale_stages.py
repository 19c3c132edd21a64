"""bench/scale_stages.py on a real (tiny) index version with an approximate tier 1: every
stage is timed, FAISS's searches are counted apart from the exact re-scoring, the record
holds each version, and the reader is left as it was (its methods unpatched)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from bench import scale_stages
from hmpf.config import parse_config
from hmpf.datasets import dataset_root
from hmpf.index.reader import IndexReader
from indexer.build import BuildOptions, build

CONFIG = {
    "name": "stages-test",
    "tiers": [{"methods": ["hog", "gist"], "k": 3}, {"methods": ["gist", "sad"], "k": 1}],
}


@pytest.fixture(scope="module")
def versions(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    root = dataset_root() / "gardens_point"
    if not (root / "day_right").is_dir():
        pytest.skip(f"Gardens Point not found under {root}")
    base = tmp_path_factory.mktemp("stages")
    refs, queries = base / "refs", base / "queries"
    refs.mkdir()
    queries.mkdir()
    for p in sorted((root / "day_right").iterdir())[:12]:
        shutil.copy(p, refs / p.name)
    for p in sorted((root / "night_right").iterdir())[:3]:
        shutil.copy(p, queries / p.name)
    exact, approx = base / "exact", base / "approx"
    build(parse_config(CONFIG), refs, exact, options=BuildOptions(workers=1, progress=False))
    opts = BuildOptions(workers=1, progress=False, faiss={"*": "PCA8:2,SQfp16,k2"})
    build(parse_config(CONFIG), refs, approx, options=opts)
    return exact, approx, queries


def test_stages_of_an_exact_and_an_approximate_tier_1(versions, tmp_path: Path) -> None:
    exact, approx, queries = versions
    search, rescore = IndexReader.search, IndexReader._approx_scores
    out = tmp_path / "stages.json"
    scale_stages.main(
        ["--index", str(exact), str(approx), "--queries", str(queries), "--frames", "2"]
        + ["--approx-k", "5", "--json", str(out)]
    )
    assert IndexReader.search is search and IndexReader._approx_scores is rescore
    rec = json.loads(out.read_text())
    assert rec["preset"] == "stages-test" and rec["machine"] and rec["digest"]
    by = {Path(v["index"]).name: v for v in rec["versions"]}
    assert set(by) == {"exact", "approx"}
    for v in by.values():
        assert v["references"] == 12 and v["frames"] == 2 and len(v["matches"]) == 2
        assert v["approx_k"] == 5  # the reader re-scored as many rows as asked
        assert set(v["p50_ms"]) == set(scale_stages.STAGES)
        assert all(0 <= m < 12 for m in v["matches"])
        assert v["p50_ms"]["extract"] > 0 and v["p50_ms"]["hierarchy"] > 0
    # Only the approximate version searches FAISS and re-scores; the exact one does neither.
    assert by["approx"]["approximate_tier1"] == ["hog", "gist"]
    assert by["exact"]["approximate_tier1"] == []
    assert by["approx"]["p50_ms"]["faiss"] > 0 and by["approx"]["p50_ms"]["rescore"] > 0
    assert by["exact"]["p50_ms"]["faiss"] == 0 and by["exact"]["p50_ms"]["rescore"] == 0
    assert by["approx"]["faiss_params"] is None


def test_a_version_searched_with_other_faiss_parameters(versions, tmp_path: Path) -> None:
    """``FOLDER@PARAMS``: the version's approximate methods are searched with them (a
    parameter its FAISS type lacks is an error, not ignored); the record says which."""
    from hmpf.index.layout import IndexBuildError

    _, approx, queries = versions
    out = tmp_path / "stages.json"
    args = ["--queries", str(queries), "--frames", "1", "--rounds", "1", "--json", str(out)]
    scale_stages.main(["--index", str(approx), f"{approx}@k_factor_rf=4", *args])
    rec = json.loads(out.read_text())
    assert [v["faiss_params"] for v in rec["versions"]] == [None, "k_factor_rf=4"]
    with pytest.raises(IndexBuildError, match="a scan in front"):
        scale_stages.main(["--index", f"{approx}@k_factor_front=2", *args])


def test_frames_and_rounds_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        scale_stages.main(["--index", str(tmp_path), "--frames", "0"])
