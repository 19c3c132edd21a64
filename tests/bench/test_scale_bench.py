"""bench/scale.py end to end on a small real version: ``write`` plants day_left's real rows
among synthetic distractors and publishes a version that ``hmpf-index verify`` accepts;
``measure`` computes recall against its own exact search (1.0 where the re-scoring covers
the map, as brute force says) and serves the version with the real ``hmpf-serve``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench import scale
from hmpf.datasets import dataset_root, list_images
from hmpf.index.ann import faiss_module
from hmpf.index.reader import IndexReader
from indexer import build

#: one cheap global method, so that the source build and the queries take seconds
CONFIG = "name: scale-bench-test\ntiers:\n  - methods: [gist]\n    k: 5\n"
#: more than the reader's fixed sample of 1024 rows, which it always re-scores
REFS = 3000
NORDLAND = 40


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict, Path]:
    datasets = dataset_root()
    for folder in (scale.PLANTED_FOLDER, scale.QUERY_FOLDER, scale.NORDLAND_FOLDER):
        if not (datasets / folder).is_dir():
            pytest.skip(f"{folder} not found under {datasets}")
    base = tmp_path_factory.mktemp("scale")
    config = base / "config.yaml"
    config.write_text(CONFIG)
    out, record, cache = base / "v3000", base / "write.json", base / "cache"
    train_rows = build.FAISS_TRAIN_ROWS
    try:
        scale.main(
            ["write", "--refs", str(REFS), "--out", str(out), "--config", str(config)]
            + ["--source", str(base / "source"), "--nordland", str(NORDLAND)]
            + ["--faiss", "gist=PCA64:16,SQfp16,S8x2", "--faiss-params", "k_factor_rf=4"]
            + ["--components", "16", "--route-len", "100", "--check"]
            + ["--datasets", str(datasets), "--cache-dir", str(cache), "--json", str(record)]
        )
    finally:
        build.FAISS_TRAIN_ROWS = train_rows  # write sets the build's training sample
    return out, base / "source", json.loads(record.read_text()), cache


@pytest.fixture(autouse=True)
def _faiss_threads():
    """measure searches on one FAISS thread, as a replica does; the other tests get their
    pool back."""
    faiss = faiss_module()
    threads = faiss.omp_get_max_threads()
    yield
    faiss.omp_set_num_threads(threads)


def test_write_plants_the_real_rows_among_distractors(written) -> None:
    out, source, rec, _ = written
    assert rec["references"] == REFS and rec["preset"] == "scale-bench-test"
    assert rec["faiss"]["factories"] == {"gist": "PCA64:16,SQfp16,S8x2"}
    assert rec["checks"]["verify"]["rc"] == 0 and rec["checks"]["info"]["rc"] == 0
    lo, hi = rec["planted"]["rows"]
    assert hi - lo == 200 and lo == (REFS - 200) // 2  # the middle by default
    with IndexReader(source) as src, IndexReader(out) as v:
        assert v.n_rows == REFS and v.faiss_info("gist")["factory"] == "PCA64:16,SQfp16,S8x2"
        planted = scale.planted_rows(v)
        assert list(planted) == list(range(lo, hi))
        day_left = [i for i, s in enumerate(src.refs.sources) if s.endswith(scale.PLANTED_FOLDER)]
        real = np.asarray(src.global_matrix("gist"))[day_left]
        rows = np.asarray(v.global_matrix("gist"))
        # the planted rows are day_left's own, in order; the distractors are new rows,
        # finished as Gist finishes its descriptors (non-negative)
        np.testing.assert_array_equal(rows[lo:hi], real)
        others = np.delete(rows, planted, axis=0)
        assert (others >= 0).all() and len(np.unique(others, axis=0)) == REFS - 200
        names = [v.refs.names[i] for i in planted]
        assert names == [src.refs.names[i] for i in day_left]


def test_measure_recall_against_its_own_exact_search_and_a_real_serve(written, tmp_path) -> None:
    out, _, _, cache = written
    record = tmp_path / "measure.json"
    scale.main(
        ["measure", "--index", str(out), "--approx-k", str(REFS), "16"]
        + ["--no-reload", "--warmup", "2", "--serve-params", "k_factor_front=3"]
        + ["--datasets", str(dataset_root()), "--cache-dir", str(cache), "--json", str(record)]
    )
    rec = json.loads(record.read_text())
    rows = {r["approx_k"]: r for r in rec["recall"]["gist"]["settings"]}
    # re-scoring every row exactly is exact search: the same top 100 and top 10
    assert rows[REFS]["recall_at_100"] == 1.0 and rows[REFS]["recall_at_10"] == 1.0
    assert rows[REFS]["right_in_approx_top10"] == rows[REFS]["right_in_exact_top10"]
    # FAISS's 16 rows and the sample cannot hold every query's top 100
    assert rows[16]["recall_at_100"] < 1.0
    assert all(r["faiss_ms_p50"] > 0 for r in rows.values())
    serve = rec["serve"]
    queries = len(list_images(dataset_root() / scale.QUERY_FOLDER))
    assert serve["queries"] == queries and serve["approx_k"] == REFS
    assert serve["faiss_params"] == "k_factor_front=3"  # hmpf-serve took them (else: no start)
    assert 0.0 <= serve["recall_at_1"] <= 1.0 and 0 < serve["p50_ms"] <= serve["p99_ms"]
    assert serve["first_answer_s"] >= serve["ready_s"] > 0
    assert serve["verification"]["state"] == "passed"


def test_write_refuses_a_source_of_another_config(written, tmp_path) -> None:
    _, source, _, cache = written
    other = tmp_path / "other.yaml"
    other.write_text(CONFIG.replace("k: 5", "k: 4"))
    with pytest.raises(SystemExit, match="built for"):
        scale.main(
            ["write", "--refs", "300", "--out", str(tmp_path / "v"), "--config", str(other)]
            + ["--source", str(source), "--cache-dir", str(cache)]
        )


def test_stored_settings_bring_back_the_built_front_factor() -> None:
    """What ``measure`` sets after trying other settings: the factory's ``G`` first, then
    the stored parameters (which win); a search with them answers as the index did before
    any setting was tried."""
    from hmpf.index.ann import build_faiss, set_search_params
    from hmpf.methods.base import MetricSpec

    front = {"factory": "PCA32:16,SQfp16,S8x4,k4", "params": "k_factor_rf=4"}
    assert scale.stored_settings(front) == "k_factor_rf=4,k_factor_front=4,k_factor_rf=4"
    assert scale.stored_settings({**front, "params": "k_factor_front=2"}) == (
        "k_factor_rf=4,k_factor_front=4,k_factor_front=2"
    )
    assert scale.stored_settings({"factory": "PCA32:16,SQfp16,B64", "params": None}) == (
        "k_factor_rf=8,k_factor_front=8"
    )
    assert scale.stored_settings({"factory": "PCA32:16,SQfp16,FS8x2", "params": ""}) == (
        "k_factor_rf=8,k_factor_front=2"
    )
    assert scale.stored_settings({"factory": "PCA256:64,SQfp16,k2", "params": ""}) == (
        "k_factor_rf=2"
    )
    assert scale.stored_settings({"factory": "IVF63,PQ64np", "params": ""}) == ""
    rng = np.random.default_rng(3)
    x = (rng.standard_normal((2000, 20)) @ rng.standard_normal((20, 48))).astype(np.float32)
    q = x[:15] + 0.3 * rng.standard_normal((15, 48)).astype(np.float32)
    index, _ = build_faiss(x, MetricSpec("l2", 1.0), str(front["factory"]))
    before = index.search(q, 10)
    set_search_params(index, "k_factor_rf=1,k_factor_front=1")
    assert not np.array_equal(index.search(q, 10)[1], before[1])
    set_search_params(index, scale.stored_settings({**front, "params": ""}))  # F from k4
    assert np.array_equal(index.search(q, 10)[1], before[1])


def test_the_disk_reserve_scales_with_the_version() -> None:
    # A test's small version may be written on a disk with a few GB free (CI's clean
    # machine had 7.2 GB); a million references' 31 GB still keep 8 GB free.
    assert scale._reserve(0.2e9) == 1e9
    assert scale._reserve(3e9) == 3e9
    assert scale._reserve(31e9) == 8e9
