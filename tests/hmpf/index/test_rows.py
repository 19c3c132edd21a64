"""Rows read on demand (:mod:`hmpf.index.rows`) against the matrices held in memory: the
same rows bit for bit, the same tier-1 scores and answers, a bounded feature cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.imageio import load_image
from hmpf.index import IndexReader
from hmpf.index import reader as reader_module
from hmpf.index.rows import DiskRows, LruCache, disk_rows, widen
from hmpf.index.storage import open_h5
from indexer.build import BuildOptions, build

CONFIG = {
    "name": "rows-test",
    "methods": {"kaze": {"max_keypoints": 40}},
    "tiers": [
        {"methods": ["hog", "gist"], "k": 5},
        {"methods": ["gist", "sad", "kaze"], "k": 1},
    ],
}


@pytest.fixture(scope="module")
def gp(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """16 Gardens Point day_right references and 4 night_right queries."""
    from hmpf.datasets import dataset_root

    root = dataset_root() / "gardens_point"
    if not (root / "day_right").is_dir():
        pytest.skip(f"Gardens Point not found under {root}")
    folder = tmp_path_factory.mktemp("gp") / "refs"
    folder.mkdir()
    for p in sorted((root / "day_right").iterdir())[:16]:
        shutil.copy(p, folder / p.name)
    return folder, sorted((root / "night_right").iterdir())[:4]


@pytest.fixture(scope="module")
def exact_index(gp, tmp_path_factory) -> Path:
    index = tmp_path_factory.mktemp("exact") / "map"
    build(parse_config(CONFIG), gp[0], index, options=BuildOptions(workers=1, progress=False))
    return index


@pytest.fixture(
    scope="module",
    params=[
        "IVF2,Flat|nprobe=1",
        "PCA8:2,SQfp16,k2|",
        "PCA8:2,SQfp16,HNSW4,k2|",
        "PCA8:4,SQfp16,S2x4,k2|k_factor_front=2",
    ],
)
def approx_index(gp, tmp_path_factory, request) -> Path:
    """The same references on an approximate tier 1: IVF, and the projected scan (with a
    scalar short scan, with an HNSW short list, and with a scan in front whose G the
    build's search parameters change)."""
    factory, params = request.param.split("|")
    index = tmp_path_factory.mktemp("approx") / "map"
    opts = BuildOptions(workers=1, progress=False, faiss={"*": factory}, faiss_params={"*": params})
    build(parse_config(CONFIG), gp[0], index, options=opts)
    return index


def test_disk_rows_equal_the_stored_matrix(exact_index):
    with IndexReader(exact_index, mmap=False) as r:
        held = {mid: np.asarray(r.global_matrix(mid)) for mid in ("hog", "gist", "sad")}
        f = open_h5(r.path / "references.h5")
        try:
            rng = np.random.default_rng(0)
            for mid, want in held.items():
                rows = disk_rows(f["global"][mid])
                assert isinstance(rows, DiskRows)
                assert rows.shape == want.shape and rows.dtype == want.dtype
                idx = rng.integers(-len(want), len(want), 40)  # unsorted, repeats, negative
                assert np.array_equal(rows[idx], want[idx])
                assert np.array_equal(rows[3], want[3])
                assert np.array_equal(rows[2:9], want[2:9])
                assert np.array_equal(rows[::3], want[::3])
                assert np.array_equal(np.asarray(rows), want)
                assert np.array_equal(rows[np.array([], np.int64)], want[:0])
                runs = np.array([7, 5, 6, 11, 10, 0, 1, 6])  # three runs, out of order, a repeat
                calls = rows.stats.calls
                assert np.array_equal(rows[runs], want[runs])
                assert rows.stats.calls - calls == 3  # one read per run of consecutive rows
                with pytest.raises(IndexError):
                    rows[np.array([len(want)])]
                rows.close()
                with pytest.raises(ValueError, match="after close"):
                    rows[0]
        finally:
            f.close()


def test_which_methods_are_read_on_demand(exact_index, approx_index):
    with IndexReader(exact_index) as r:  # exact tier 1: held; sad (tier 2 only): on demand
        assert [r.on_demand(m) for m in ("hog", "gist", "sad")] == [False, False, True]
        assert isinstance(r.global_matrix("sad"), DiskRows)
        assert isinstance(r.global_matrix("hog"), np.ndarray)
    with IndexReader(approx_index) as r:  # approximate tier 1: every global method
        assert all(isinstance(r.global_matrix(m), DiskRows) for m in ("hog", "gist", "sad"))
    with IndexReader(approx_index, mmap=False) as r:  # asked to hold everything
        assert all(isinstance(r.global_matrix(m), np.ndarray) for m in ("hog", "gist", "sad"))


def _answers(reader: IndexReader, queries: list[Path]) -> list[tuple]:
    hier = reader.hierarchy()
    out = []
    for q in queries:
        feats = reader.extract_query(load_image(q))
        score_fn = reader.scorer(feats)
        res = hier.run(score_fn, reader.n)
        tier1 = {m: score_fn(m, None) for m in reader.config.tiers[0].methods}
        out.append((res.match, res.final_candidates.tolist(), tier1))
    return out


@pytest.mark.parametrize("sample", [4, 1024])
def test_on_demand_rows_answer_as_rows_in_memory(approx_index, gp, monkeypatch, sample):
    """An approximate tier 1 with rows on demand and a resident sample scores exactly as
    the same reader holding every matrix in memory, and as the definition (FAISS's
    candidates and the sample scored exactly, every other row the worst of those)."""
    monkeypatch.setattr(reader_module, "SAMPLE_SIZE", sample)
    with IndexReader(approx_index) as lazy, IndexReader(approx_index, mmap=False) as held:
        got, want = _answers(lazy, gp[1]), _answers(held, gp[1])
        for (m1, c1, t1), (m2, c2, t2) in zip(got, want, strict=True):
            assert (m1, c1) == (m2, c2)
            for mid in t1:
                np.testing.assert_allclose(t1[mid], t2[mid], rtol=1e-6)
        assert lazy.read_stats.bytes > 0  # the candidates' rows came from disk
        # the definition, from the whole matrix in memory
        feats = held.extract_query(load_image(gp[1][0]))
        for mid in held.config.tiers[0].methods:
            m, x = held.methods[mid], np.asarray(held.global_matrix(mid))
            ids, _ = held.search(mid, feats[mid], held.approx_k)
            cand = np.union1d(ids, held._sample)
            exact = m.scores(feats[mid], x, cand)
            want_row = np.full(held.n_rows, exact.min() if m.higher_is_better else exact.max())
            want_row[cand] = exact
            np.testing.assert_allclose(lazy.scorer(feats)(mid, None), want_row, rtol=1e-6)


def test_local_features_cached_and_bounded(exact_index):
    with IndexReader(exact_index) as r:
        idx = np.array([5, 1, 5, 7])
        first = r.local_features("kaze", idx)
        read = r.read_stats.bytes
        assert read > 0 and r.read_stats.rows == 3  # 3 distinct rows read once each
        again = r.local_features("kaze", idx)
        assert r.read_stats.bytes == read  # from the cache
        for a, b in zip(first, again, strict=True):
            assert np.array_equal(a.keypoints, b.keypoints)
            assert np.array_equal(a.descriptors, b.descriptors)
    with IndexReader(exact_index, local_cache_bytes=0) as r:
        r.local_features("kaze", np.array([1, 2]))
        read = r.read_stats.bytes
        r.local_features("kaze", np.array([1, 2]))
        assert r.read_stats.bytes == 2 * read and len(r.local_cache) == 0


def test_lru_cache_stays_within_its_bound():
    cache = LruCache(100)
    for i in range(10):
        cache.put(i, i, 30)
        assert cache.nbytes <= 100
    assert len(cache) == 3 and cache.lookup(9) == (True, 9) and cache.lookup(0) == (False, None)
    cache.lookup(7)  # 7 is now the most recent: 8 goes first
    cache.put("x", "x", 30)
    assert cache.lookup(8) == (False, None) and cache.lookup(7) == (True, 7)
    cache.put("too big", 0, 101)
    assert cache.lookup("too big") == (False, None)
    assert cache.get("y", lambda: 5, lambda v: 10) == 5 and cache.lookup("y") == (True, 5)


@pytest.mark.parametrize("torch_loaded,block", [(True, None), (False, None), (False, 10_000)])
def test_widen_is_numpys_conversion_for_every_half_float(torch_loaded, block, monkeypatch):
    """Every float16 bit pattern (tiled past the size torch takes over) widens to numpy's
    float32, bit for bit (NaN to NaN), with torch loaded and without (OpenCV: in one call,
    and a block at a time with a small block, so the last one is a part)."""
    import sys

    from hmpf.index import rows

    if torch_loaded:
        pytest.importorskip("torch")
    else:
        monkeypatch.delitem(sys.modules, "torch", raising=False)
        if block is not None:
            monkeypatch.setattr(rows, "_WIDEN_BLOCK", block)
    half = np.tile(np.arange(1 << 16, dtype=np.uint16), 2).view(np.float16).reshape(-1, 64)
    got, want = widen(half, np.float32), half.astype(np.float32)
    assert got.dtype == np.float32 and got.shape == want.shape
    nan = np.isnan(want)
    assert np.array_equal(np.isnan(got), nan)
    assert np.array_equal(got[~nan].view(np.uint32), want[~nan].view(np.uint32))
    small = half[:2]  # below the size torch takes over, and other dtypes: numpy's astype
    assert np.array_equal(widen(small, np.float32), small.astype(np.float32), equal_nan=True)
    assert widen(want, np.float32) is want


def test_a_versions_stored_search_parameters_reach_its_reader(approx_index):
    """What ``--faiss-params`` stored is what the reader searches with: IVF's ``nprobe``,
    and ``k_factor_front`` (a scan in front's G, not a FAISS name)."""
    from hmpf.index.ann import faiss_module

    faiss = faiss_module()
    with IndexReader(approx_index) as r:
        info = r.faiss_info("hog")
        assert info is not None
        index = r.faiss_index("hog")
        if info["factory"].startswith("IVF"):
            assert faiss.extract_index_ivf(index).nprobe == 1  # FAISS's default is 1 too
            assert info["params"] == "nprobe=1"
        elif ",S2x4" in info["factory"]:
            outer = faiss.downcast_index(faiss.downcast_index(index).index)
            assert faiss.downcast_index(outer.base_index).k_factor == 2.0  # built with 4
        else:
            assert info["params"] == ""


def test_search_parameters_set_on_top_of_the_stored_ones(approx_index, exact_index):
    """:meth:`IndexReader.set_faiss_params` (hmpf-serve's ``faiss_params``): per method or
    ``"*"``, after the stored ones; a method that is not approximate is a ConfigError, a
    parameter its FAISS type lacks an IndexBuildError; an exact version has nothing to set."""
    from hmpf.errors import ConfigError
    from hmpf.index.ann import faiss_module
    from hmpf.index.layout import IndexBuildError

    faiss = faiss_module()

    def refine(index):
        return faiss.downcast_index(faiss.downcast_index(index).index)

    with IndexReader(approx_index) as r:
        assert r.approximate_methods() == ["hog", "gist"]
        factory = r.faiss_info("hog")["factory"]
        with pytest.raises(ConfigError, match="'sad'.*those: hog, gist"):
            r.set_faiss_params({"sad": "nprobe=2"})
        if factory.startswith("IVF"):
            r.set_faiss_params({"hog": "nprobe=2"})
            assert faiss.extract_index_ivf(r.faiss_index("hog")).nprobe == 2
            assert faiss.extract_index_ivf(r.faiss_index("gist")).nprobe == 1  # stored
        elif ",S2x4" in factory:
            r.set_faiss_params({"*": "k_factor_rf=3"})  # on top: the stored G = 2 stays
            assert refine(r.faiss_index("hog")).k_factor == 3.0
            assert faiss.downcast_index(refine(r.faiss_index("hog")).base_index).k_factor == 2.0
            r.set_faiss_params({"*": "k_factor_front=3", "gist": "k_factor_front=1"})
            for mid, front in (("hog", 3.0), ("gist", 1.0)):
                assert faiss.downcast_index(refine(r.faiss_index(mid)).base_index).k_factor == front
        else:
            r.set_faiss_params({"*": "k_factor_rf=3"})
            assert refine(r.faiss_index("hog")).k_factor == 3.0
            with pytest.raises(IndexBuildError, match="method 'gist'.*a scan in front"):
                r.set_faiss_params({"gist": "k_factor_front=2"})
        ids = r.search("hog", r.global_matrix("hog")[3], 5)[0]
        assert len(ids) == 5 and 3 in ids
    with IndexReader(exact_index) as r:
        assert r.approximate_methods() == []
        r.set_faiss_params({"*": "nprobe=2"})
        with pytest.raises(ConfigError, match="those: none"):
            r.set_faiss_params({"gist": "nprobe=2"})
