"""The projected-scan FAISS type (``PCA<D>:<d>,<codes>[,k<F>]``) against brute force:
what it returns is what a scan of the projected rows returns, it keeps the exact
neighbours where the rows live in fewer dimensions than ``D``, and it survives the
round trips an index version puts it through (write / read, reset / refill)."""

from __future__ import annotations

import numpy as np
import pytest

from hmpf.index.ann import (
    ProjectedSpec,
    build_faiss,
    faiss_module,
    pca_rows,
    projected_spec,
    read_faiss,
    search_faiss,
    set_search_params,
)
from hmpf.index.layout import IndexBuildError
from hmpf.methods.base import MetricSpec

L2 = MetricSpec("l2", 1.0)


def _rows(n: int = 2000, d: int = 64, rank: int = 24, noise: float = 0.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((n, rank)) @ rng.standard_normal((rank, d)) + 3.0
    x += noise * rng.standard_normal((n, d))
    return x.astype(np.float32)


def _brute(x: np.ndarray, q: np.ndarray, k: int) -> np.ndarray:
    d2 = ((q[:, None, :].astype(np.float64) - x[None].astype(np.float64)) ** 2).sum(-1)
    return np.argsort(d2, axis=1, kind="stable")[:, :k]


def test_spec_parsing():
    spec = ProjectedSpec
    assert projected_spec("PCA1024:128,SQfp16") == spec(1024, 128, "SQfp16", 8)
    assert projected_spec("PCA 256:32, SQ8, k16") == spec(256, 32, "SQ8", 16)
    assert projected_spec("PCA1024:128,SQfp16,B256") == spec(1024, 128, "SQfp16", 8, 256, 8)
    assert projected_spec("PCA1024:128,SQ8,B64x16,k4") == spec(1024, 128, "SQ8", 4, 64, 16)
    assert projected_spec("PCA1024:128,SQfp16,PQ64x4fs") == spec(1024, 128, "SQfp16", 8, pq=64)
    assert projected_spec("PCA256:64,SQfp16,PQ32x4fs,k2") == spec(256, 64, "SQfp16", 2, pq=32)
    assert projected_spec("PCA1024:128,SQfp16,HNSW32") == spec(1024, 128, "SQfp16", 8, hnsw=32)
    assert projected_spec("PCA256:64,SQ8,HNSW16,k4") == spec(256, 64, "SQ8", 4, hnsw=16)
    assert projected_spec("PCA1024:128,SQfp16,S64") == spec(
        1024, 128, "SQfp16", 8, pre=64, pre_factor=4
    )
    assert projected_spec("PCA256:64,SQ8,S32x2,k4") == spec(256, 64, "SQ8", 4, pre=32, pre_factor=2)
    assert tuple(projected_spec("PCA256:64,SQ8,S32x2,k4")) == (
        (256, 64, "SQ8", 4, 0, 0, 0, 0, 32, 2, 0, 0)
    )
    assert projected_spec("PCA1024:128,SQfp16,FS64") == spec(
        1024, 128, "SQfp16", 8, fast=64, fast_factor=8
    )
    assert projected_spec("PCA256:64,SQ8,FS32x4,k2") == spec(
        256, 64, "SQ8", 2, fast=32, fast_factor=4
    )
    for other in (
        "Flat",
        "IVF64,PQ8",
        "PCA256,SQ8",
        "PCA256:32,PQ8",
        "PCA256:32,SQfp16,k",
        "PCA256:32,SQfp16,B",
        "PCA256:32,SQfp16,k8,B64",
        "PCA256:32,SQfp16,B64x",
        "PCA256:32,SQfp16,B0",
        "PCA256:32,SQfp16,PQ0x4fs",
        "PCA256:32,SQfp16,PQ16",
        "PCA256:32,SQfp16,PQ16x8fs",
        "PCA256:32,SQfp16,B64,PQ16x4fs",
        "PCA256:32,SQfp16,k8,PQ16x4fs",
        "PCA256:32,SQfp16,HNSW",
        "PCA256:32,SQfp16,HNSW0",
        "PCA256:32,SQfp16,PQ16x4fs,HNSW32",
        "PCA256:32,SQfp16,k8,HNSW32",
        "PCA256:32,SQfp16,S",
        "PCA256:32,SQfp16,S0",
        "PCA256:32,SQfp16,S16x",
        "PCA256:32,SQfp16,B64,S16",
        "PCA256:32,SQfp16,S16,HNSW32",
        "PCA256:32,SQfp16,k8,S16",
        "PCA256:32,SQfp16,FS",
        "PCA256:32,SQfp16,FS0",
        "PCA256:32,SQfp16,FS16x",
        "PCA256:32,SQfp16,S8,FS16",
        "PCA256:32,SQfp16,k8,FS16",
    ):
        assert projected_spec(other) is None


def test_pca_rows_are_the_principal_directions():
    x = _rows(noise=0.01)
    mean, comps = pca_rows(x, 8)
    np.testing.assert_allclose(mean, x.mean(0, dtype=np.float64), rtol=1e-5)
    np.testing.assert_allclose(comps @ comps.T, np.eye(8), atol=1e-6)
    # the same subspace as numpy's SVD of the centred rows, largest variance first
    _, s, vt = np.linalg.svd(x - x.mean(0), full_matrices=False)
    proj = comps @ vt[:8].T
    np.testing.assert_allclose(np.abs(np.linalg.det(proj)), 1.0, atol=1e-4)
    var = ((x - mean) @ comps.T).var(0)
    assert np.all(np.diff(var) <= 1e-6 * var[0])


def test_equals_a_scan_of_the_projected_rows_when_the_short_list_covers_the_map():
    """With F x k >= N every row reaches the re-ranking on all D dimensions: the answer is
    brute force over the projected rows (fp16 codes, so up to their rounding)."""
    x = _rows(n=500, noise=0.3)
    q = _rows(n=20, noise=0.3, seed=1)
    index, metric = build_faiss(x, L2, "PCA32:4,SQfp16,k64")
    assert metric == L2 and index.ntotal == len(x)
    mean, comps = pca_rows(x, 32)
    y = ((x - mean) @ comps.T).astype(np.float16).astype(np.float32)
    qy = ((q - mean) @ comps.T).astype(np.float32)
    dist, ids = index.search(q, 10)
    want = _brute(y, qy, 10)
    assert (ids == want).mean() >= 0.95  # fp16 rounding may swap near-ties
    np.testing.assert_allclose(dist[:, 0], ((y[ids[:, 0]] - qy) ** 2).sum(1), rtol=2e-3, atol=1e-3)


def test_keeps_the_exact_neighbours_of_rows_of_lower_rank():
    """Rows of rank 24 projected on 32 directions lose nothing: the top 10 are the exact
    top 10 of the original rows, through the short scan on 16 dimensions and F = 32 (the
    queries' own part outside the rows' subspace adds the same to every distance)."""
    x = _rows(rank=24)
    q = x[::67] + 0.05 * np.random.default_rng(3).standard_normal((len(x[::67]), 64)).astype(
        np.float32
    )
    index, _ = build_faiss(x, L2, "PCA32:16,SQfp16,k32")
    _, ids = index.search(q, 10)
    want = _brute(x, q, 10)
    hits = np.mean([len(np.intersect1d(a, b)) / 10 for a, b in zip(ids, want, strict=True)])
    assert hits >= 0.99


def test_round_trips(tmp_path):
    faiss = faiss_module()
    x = _rows(noise=0.2)
    q = x[:7] + 0.01
    index, _ = build_faiss(x, L2, "PCA40:10,SQ8,k4")
    d0, i0 = index.search(q, 5)
    path = tmp_path / "t.faiss"
    faiss.write_index(index, str(path))
    back = read_faiss(path)
    d1, i1 = back.search(q, 5)
    assert np.array_equal(i0, i1) and np.array_equal(d0, d1)
    back.reset()
    assert back.ntotal == 0
    for lo in range(0, len(x), 300):  # refilled block by block, as a build does
        back.add(x[lo : lo + 300])
    d2, i2 = back.search(q, 5)
    # the projection of a block may round differently from that of all rows at once
    assert np.array_equal(i0, i2)
    np.testing.assert_allclose(d0, d2, rtol=1e-5)
    # the short list's length is a search parameter
    set_search_params(back, "k_factor_rf=1")
    refine = faiss.downcast_index(faiss.downcast_index(back).index)
    assert refine.k_factor == 1.0


def test_l1_methods_get_an_l2_proxy():
    x = _rows(n=300, noise=0.2)
    _, metric = build_faiss(x, MetricSpec("l1", 0.5), "PCA16:4,SQfp16")
    assert metric == MetricSpec("l2", 1.0, proxy=True)


@pytest.mark.parametrize(
    ("factory", "match"),
    [
        ("PCA64:8,SQfp16", "64 < 64"),
        ("PCA32:32,SQfp16", "32 < 32"),
        ("PCA8:16,SQ8", "16 < 8"),
        ("PCA32:8,SQfp16,B33", "33 <= 32"),
        ("PCA32:8,SQfp16,B16x0", "factor above 0"),
        ("PCA32:8,SQfp16,PQ3x4fs", "3 sub-quantizers do not divide 8"),
        ("PCA32:8,SQfp16,S8", "8 < 8 dimensions in front"),
        ("PCA32:8,SQfp16,S4x0", "factor above 0"),
        ("PCA32:8,SQfp16,FS3", "3 sub-quantizers do not divide 8"),
        ("PCA32:8,SQfp16,FS4x0", "factor above 0"),
    ],
)
def test_bad_sizes_are_build_errors(factory, match):
    with pytest.raises(IndexBuildError, match=match):
        build_faiss(_rows(n=200), L2, factory)


def test_memory_mapped_codes_search_as_read_ones(tmp_path):
    """A reader maps the codes of a flat-codes type instead of reading them: the same
    answers; a type that is not flat codes (IVF) still loads."""
    faiss = faiss_module()
    x = _rows(n=3000, noise=0.2)
    q = x[:9] + 0.01
    index, _ = build_faiss(x, L2, "PCA48:12,SQfp16,k4")
    path = tmp_path / "t.faiss"
    faiss.write_index(index, str(path))
    read, mapped = read_faiss(path, "k_factor_rf=2"), read_faiss(path, "k_factor_rf=2", mmap=True)
    for a, b in zip(read.search(q, 20), mapped.search(q, 20), strict=True):
        assert np.array_equal(a, b)
    ivf, _ = build_faiss(x, L2, "IVF8,Flat")  # not flat codes: read as before
    faiss.write_index(ivf, str(path))
    assert read_faiss(path, "nprobe=8", mmap=True).ntotal == len(x)


def _projected(x: np.ndarray, q: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """The rows and the queries on the rows' top ``dim`` principal directions (centred)."""
    mean, comps = pca_rows(x, dim)
    return (
        ((x - mean) @ comps.T).astype(np.float32),
        ((q - mean) @ comps.T).astype(np.float32),
    )


def _short_list_search(spec: str, x: np.ndarray, q: np.ndarray, k: int) -> tuple:
    """A projected-scan index of ``spec`` over ``x`` searched for ``q``'s top ``k``:
    (distances, ids, the rows and queries projected on the first 32 principal
    coordinates, the index that makes the short list, the whole index). Keep the whole
    index while using the short list's: FAISS frees its parts with it."""
    faiss = faiss_module()
    index, _ = build_faiss(x, L2, spec)
    dist, ids = index.search(q, k)
    y, qy = _projected(x, q, 32)
    refine = faiss.downcast_index(faiss.downcast_index(index).index)
    return dist, ids, y, qy, faiss.downcast_index(refine.base_index), index


def _assert_ranked_by_fp16_codes(
    dist: np.ndarray, ids: np.ndarray, y: np.ndarray, qy: np.ndarray
) -> None:
    """The rows that came back are ranked by the squared distances of their fp16 codes on
    all the projected dimensions."""
    y16 = y.astype(np.float16).astype(np.float32)
    want = ((y16[ids] - qy[:, None, :]) ** 2).sum(-1)
    np.testing.assert_allclose(dist, want, rtol=2e-3, atol=1e-3)
    assert (np.diff(dist, axis=1) >= 0).all()


def _assert_short_list_then_ranked(
    short, codes: np.ndarray, size: int, least: float, searched: tuple
) -> None:
    """The short list (``short`` searched for the ``size`` nearest) overlaps brute force
    over the rows' ``codes`` on the first 16 coordinates by at least ``least``; the rows
    that came back (``searched``: distances, ids, projected rows and queries) are among
    it and ranked by their fp16 codes on all the projected dimensions."""
    dist, ids, y, qy = searched
    want = _brute(codes, qy[:, :16], size)
    _, got = short.search(qy, size)
    overlap = np.mean([len(np.intersect1d(a, b)) / size for a, b in zip(got, want, strict=True)])
    assert overlap >= least
    for row, short_list in zip(ids, got, strict=True):
        assert set(row) <= set(short_list)
    _assert_ranked_by_fp16_codes(dist, ids, y, qy)


def _low_rank_hits(spec: str, tmp_path, seed: int) -> tuple:
    """An index of ``spec`` over 4000 rows of rank 24, written to a file, and a function
    giving the share of the exact top 10 an index of it returns for noisy copies of every
    67th row: (index, path, hits)."""
    faiss = faiss_module()
    x = _rows(n=4000, rank=24)
    rng = np.random.default_rng(seed)
    q = x[::67] + 0.05 * rng.standard_normal((len(x[::67]), 64)).astype(np.float32)
    index, _ = build_faiss(x, L2, spec)
    want = _brute(x, q, 10)
    path = tmp_path / "low-rank.faiss"
    faiss.write_index(index, str(path))

    def hits(searched) -> float:
        _, got = searched.search(q, 10)
        return np.mean([len(np.intersect1d(a, b)) / 10 for a, b in zip(got, want, strict=True)])

    return index, path, hits


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) Hamming distances between rows of booleans."""
    return (a[:, None, :] != b[None, :, :]).sum(-1)


def test_binary_scan_short_list_is_the_nearest_signs_then_the_projected_ranking():
    """``B<b>x<G>``: brute force of each stage. The sign bits are those of the first b
    centred principal coordinates turned by an orthonormal rotation; the rows that come
    back are among the G x F x k nearest by their Hamming distance (every returned row's
    distance is at most the (G F k)-th smallest), and their distances are the squared
    distances of the fp16 codes on all D dimensions."""
    faiss = faiss_module()
    x = _rows(n=3000, noise=0.3)
    q = _rows(n=15, noise=0.3, seed=4)
    k = 5
    dist, ids, y, qy, short, _index = _short_list_search("PCA32:8,SQfp16,B16x4,k2", x, q, k)
    signs = faiss.downcast_index(short.base_index)
    turn = faiss.downcast_VectorTransform(signs.chain.at(0))
    a = faiss.vector_to_array(turn.A).reshape(16, 32)
    assert not a[:, 16:].any()  # the first b coordinates only
    np.testing.assert_allclose(a[:, :16] @ a[:, :16].T, np.eye(16), atol=1e-4)
    ham = _hamming(qy @ a.T > 0, y @ a.T > 0)
    cut = np.sort(ham, axis=1)[:, 4 * 2 * k - 1]
    assert (ids >= 0).all()
    assert (np.take_along_axis(ham, ids, axis=1) <= cut[:, None]).all()
    _assert_ranked_by_fp16_codes(dist, ids, y, qy)


def test_binary_scan_changes_nothing_when_its_short_list_covers_the_map():
    x = _rows(n=400, noise=0.3)
    q = _rows(n=12, noise=0.3, seed=2)
    plain, _ = build_faiss(x, L2, "PCA24:6,SQfp16,k4")
    binary, _ = build_faiss(x, L2, "PCA24:6,SQfp16,B8x100,k4")
    for a, b in zip(plain.search(q, 10), binary.search(q, 10), strict=True):
        assert np.array_equal(a, b)


def test_binary_scan_keeps_the_exact_neighbours_of_rows_of_lower_rank(tmp_path):
    """Rank-24 rows, 32 sign bits with a short list of 16 x 8 x k (1280 of 4000 rows): at
    least 97 % of the exact top 10 come back (with the plain signs of the principal
    coordinates, no rotation, 75 % did at 8 x 8 x k), also from a memory-mapped file, and
    more with a longer list (F is a search parameter)."""
    index, path, hits = _low_rank_hits("PCA32:16,SQfp16,B32x16,k8", tmp_path, 3)
    assert hits(index) >= 0.97
    assert hits(read_faiss(path, mmap=True)) == hits(index)
    assert hits(read_faiss(path, "k_factor_rf=1")) < hits(read_faiss(path, "k_factor_rf=16"))


def test_fast_scan_short_list_is_the_nearest_product_codes_then_the_projected_ranking():
    """``PQ<M>x4fs``: brute force of each stage. The short list is the F x k rows nearest
    to the query by their product codes on the first d principal coordinates (FAISS's
    fast scan rounds its look-up tables to 8 bits, so the list is compared by overlap with
    brute force over the decoded codes); the rows that come back are ranked by the squared
    distances of their fp16 codes on all D dimensions."""
    faiss = faiss_module()
    x = _rows(n=4000, noise=0.3)
    q = _rows(n=15, noise=0.3, seed=5)
    k = 10
    dist, ids, y, qy, short, _index = _short_list_search("PCA32:16,SQfp16,PQ8x4fs,k4", x, q, k)
    pq = faiss.downcast_index(short.index)
    assert isinstance(pq, faiss.IndexPQFastScan) and (pq.d, pq.M, pq.nbits) == (16, 8, 4)
    decoded = np.stack([pq.reconstruct(i) for i in range(pq.ntotal)])
    _assert_short_list_then_ranked(short, decoded, 4 * k, 0.9, (dist, ids, y, qy))


def test_fast_scan_changes_nothing_when_its_short_list_covers_the_map(tmp_path):
    """With F x k >= N every row reaches the re-ranking: the same answers as the scalar
    short scan; and the index survives a write and a memory-mapped read."""
    faiss = faiss_module()
    x = _rows(n=400, noise=0.3)
    q = _rows(n=12, noise=0.3, seed=6)
    plain, _ = build_faiss(x, L2, "PCA32:8,SQfp16,k64")
    fast, _ = build_faiss(x, L2, "PCA32:8,SQfp16,PQ4x4fs,k64")
    d0, i0 = plain.search(q, 6)
    d1, i1 = fast.search(q, 6)
    assert np.array_equal(i0, i1)
    np.testing.assert_allclose(d0, d1, rtol=1e-5)
    path = tmp_path / "t.faiss"
    faiss.write_index(fast, str(path))
    for a, b in zip(fast.search(q, 6), read_faiss(path, mmap=True).search(q, 6), strict=True):
        assert np.array_equal(a, b)


def test_hnsw_short_list_is_the_nearest_codes_then_the_projected_ranking():
    """``HNSW<M>``: brute force of each stage. The short list is (nearly: a graph search
    may miss a row) the F x k rows nearest to the query by their fp16 codes on the first d
    principal coordinates; the rows that come back are among it and ranked by the squared
    distances of their fp16 codes on all D dimensions."""
    faiss = faiss_module()
    x = _rows(n=4000, noise=0.3)
    q = _rows(n=15, noise=0.3, seed=7)
    k = 10
    index, _ = build_faiss(x, L2, "PCA32:16,SQfp16,HNSW16,k4")
    dist, ids = search_faiss(index, q, k)
    y, qy = _projected(x, q, 32)
    refine = faiss.downcast_index(faiss.downcast_index(index).index)
    short = faiss.downcast_index(refine.base_index)
    graph = faiss.downcast_index(short.index)
    assert isinstance(graph, faiss.IndexHNSWSQ) and graph.hnsw.efConstruction == 40
    graph.hnsw.efSearch = 4 * k  # the list search_faiss asks for
    codes = y[:, :16].astype(np.float16).astype(np.float32)
    _assert_short_list_then_ranked(short, codes, 4 * k, 0.95, (dist, ids, y, qy))


def test_hnsw_changes_nothing_when_its_list_covers_the_map(tmp_path):
    """A candidate list of N rows (F x k = N) visits every row the graph reaches: the plain
    scan's answers; the index survives a write and a memory-mapped read (the graph is
    read, the codes mapped); search_faiss leaves the index's own parameters as they were."""
    faiss = faiss_module()
    x = _rows(n=400, noise=0.3)
    q = _rows(n=12, noise=0.3, seed=8)
    plain, _ = build_faiss(x, L2, "PCA32:8,SQfp16,k80")
    graph, _ = build_faiss(x, L2, "PCA32:8,SQfp16,HNSW8,k80")
    d0, i0 = search_faiss(plain, q, 5)
    d1, i1 = search_faiss(graph, q, 5)
    assert np.array_equal(i0, i1)
    np.testing.assert_allclose(d0, d1, rtol=1e-5)
    path = tmp_path / "t.faiss"
    faiss.write_index(graph, str(path))
    mapped = read_faiss(path, mmap=True)
    for a, b in zip(search_faiss(graph, q, 5), search_faiss(mapped, q, 5), strict=True):
        assert np.array_equal(a, b)
    refine = faiss.downcast_index(faiss.downcast_index(mapped).index)
    hnsw = faiss.downcast_index(faiss.downcast_index(refine.base_index).index)
    assert (refine.k_factor, hnsw.hnsw.efSearch) == (80.0, 16)
    # a short list of k rows, found with a candidate list of every row: the plain scan's
    set_search_params(mapped, "k_factor_rf=1,efSearch=400")
    set_search_params(plain, "k_factor_rf=1")
    assert (refine.k_factor, hnsw.hnsw.efSearch) == (1.0, 400)
    assert np.array_equal(search_faiss(mapped, q, 5)[1], search_faiss(plain, q, 5)[1])


def test_hnsw_keeps_the_exact_neighbours_of_rows_of_lower_rank():
    """Rank-24 rows: the graph's short list keeps at least 97 % of the exact top 10 of
    4000 rows; without search_faiss's candidate list (FAISS's efSearch of 16 for a short
    list of 80 rows) fewer are kept."""
    x = _rows(n=4000, rank=24)
    rng = np.random.default_rng(9)
    q = x[::67] + 0.05 * rng.standard_normal((len(x[::67]), 64)).astype(np.float32)
    index, _ = build_faiss(x, L2, "PCA32:16,SQfp16,HNSW16,k8")
    want = _brute(x, q, 10)

    def hits(ids: np.ndarray) -> float:
        return np.mean([len(np.intersect1d(a, b)) / 10 for a, b in zip(ids, want, strict=True)])

    kept = hits(search_faiss(index, q, 10)[1])
    assert kept >= 0.97
    assert hits(index.search(q, 10)[1]) < kept


def test_scan_in_front_is_the_nearest_8bit_codes_then_the_short_scan_then_the_ranking():
    """``S<e>x<G>``: brute force of each stage. The scan in front keeps the G x F x k rows
    nearest to the query by their 8-bit codes of the first e principal coordinates; the
    short list is the F x k of those nearest by their fp16 codes on the first d; the rows
    that come back are among it and ranked by their fp16 codes on all D dimensions."""
    faiss = faiss_module()
    x = _rows(n=3000, noise=0.3)
    q = _rows(n=15, noise=0.3, seed=10)
    k = 5
    dist, ids, y, qy, scan, _index = _short_list_search("PCA32:16,SQfp16,S8x3,k4", x, q, k)
    front = faiss.downcast_index(scan.base_index)
    sq = faiss.downcast_index(front.index)
    assert isinstance(sq, faiss.IndexScalarQuantizer) and sq.d == 8
    assert sq.sq.qtype == faiss.ScalarQuantizer.QT_8bit
    decoded = sq.reconstruct_n(0, sq.ntotal)
    assert np.abs(decoded - y[:, :8]).max() <= (y[:, :8].max(0) - y[:, :8].min(0)).max() / 255
    size = 3 * 4 * k
    _, in_front = front.search(qy, size)
    want = _brute(decoded, qy[:, :8], size)
    assert (
        np.mean([len(np.intersect1d(a, b)) / size for a, b in zip(in_front, want, strict=True)])
        >= 0.99
    )
    _, short_list = scan.search(qy, 4 * k)
    y16 = y[:, :16].astype(np.float16).astype(np.float32)
    for j in range(len(q)):
        order = np.argsort(((y16[in_front[j]] - qy[j, :16]) ** 2).sum(1), kind="stable")
        assert set(short_list[j]) == set(in_front[j][order[: 4 * k]])
        assert set(ids[j]) <= set(short_list[j])
    _assert_ranked_by_fp16_codes(dist, ids, y, qy)


def _front_covering_the_map(front: str, seed: int, tmp_path) -> tuple:
    """A projected scan with the scan in front ``front`` (its list covers the 400 rows)
    answers as the plain scan, also after a write and a memory-mapped read: (rows, queries,
    the plain scan, the written file)."""
    faiss = faiss_module()
    x = _rows(n=400, noise=0.3)
    q = _rows(n=12, noise=0.3, seed=seed)
    plain, _ = build_faiss(x, L2, "PCA24:6,SQfp16,k4")
    index, _ = build_faiss(x, L2, f"PCA24:6,SQfp16,{front},k4")
    for a, b in zip(plain.search(q, 10), index.search(q, 10), strict=True):
        assert np.array_equal(a, b)
    path = tmp_path / "front.faiss"
    faiss.write_index(index, str(path))
    for a, b in zip(index.search(q, 10), read_faiss(path, mmap=True).search(q, 10), strict=True):
        assert np.array_equal(a, b)
    return x, q, plain, path


def test_scan_in_front_changes_nothing_when_its_list_covers_the_map(tmp_path):
    """With G x F x k >= N every row reaches the short scan: the plain scan's answers; the
    index survives a write and a memory-mapped read and refills block by block."""
    x, q, plain, path = _front_covering_the_map("S3x100", 11, tmp_path)
    back = read_faiss(path)
    back.reset()
    for lo in range(0, len(x), 150):
        back.add(x[lo : lo + 150])
    assert back.ntotal == len(x)
    assert np.array_equal(back.search(q, 10)[1], plain.search(q, 10)[1])


def test_scan_in_front_keeps_the_exact_neighbours_of_rows_of_lower_rank(tmp_path):
    """Rank-24 rows, the first 12 of 32 principal coordinates in front with a list of
    4 x 8 x k (320 of 4000 rows): at least 97 % of the exact top 10 come back, also from a
    memory-mapped file, and fewer with a shorter list (F is a search parameter)."""
    index, path, hits = _low_rank_hits("PCA32:16,SQfp16,S12x4,k8", tmp_path, 12)
    assert hits(index) >= 0.97
    assert hits(read_faiss(path, mmap=True)) == hits(index)
    assert hits(read_faiss(path, "k_factor_rf=1")) < hits(index)


def test_front_factor_is_a_search_parameter(tmp_path):
    """``k_factor_front=G`` sets the scan in front's G after the build: an index built with
    G = 4 and searched with G = 2 answers exactly as one built with G = 2, also beside
    FAISS's own names and from a read file; a smaller G keeps no more of the exact top 10."""
    faiss = faiss_module()
    x = _rows(n=3000, d=48, rank=20, noise=0.2, seed=5)
    q = _rows(n=20, d=48, rank=20, noise=0.2, seed=6)
    built4, _ = build_faiss(x, L2, "PCA32:16,SQfp16,S8x4,k4")
    built2, _ = build_faiss(x, L2, "PCA32:16,SQfp16,S8x2,k2")
    set_search_params(built4, "k_factor_rf=2, k_factor_front=2")
    for a, b in zip(built4.search(q, 10), built2.search(q, 10), strict=True):
        assert np.array_equal(a, b)
    set_search_params(built2, "k_factor_front=4 k_factor_rf=4")  # spaces, as FAISS takes
    set_search_params(built4, "k_factor_rf=4 k_factor_front=4")
    for a, b in zip(built4.search(q, 10), built2.search(q, 10), strict=True):
        assert np.array_equal(a, b)
    set_search_params(built2, "k_factor_front=2,k_factor_rf=2")
    path = tmp_path / "s.faiss"
    faiss.write_index(built2, str(path))
    read = read_faiss(path, "k_factor_front=4,k_factor_rf=4", mmap=True)
    set_search_params(built4, "k_factor_front=4,k_factor_rf=4")
    for a, b in zip(read.search(q, 10), built4.search(q, 10), strict=True):
        assert np.array_equal(a, b)
    want = _brute(x, q, 10)

    def hits(front: float) -> float:
        set_search_params(built4, f"k_factor_front={front}")
        got = built4.search(q, 10)[1]
        return float(np.mean([len(np.intersect1d(a, b)) for a, b in zip(got, want, strict=True)]))

    assert hits(1) <= hits(2) <= hits(8)
    assert hits(1) < hits(8)


def test_fast_scan_in_front_is_the_nearest_product_codes_then_the_short_scan_then_the_ranking():
    """``FS<M>x<G>``: brute force of each stage. The scan in front keeps the G x F x k rows
    nearest to the query by their 4-bit product codes of the first d principal coordinates
    (FAISS's fast scan rounds its look-up tables to 8 bits, so that list is compared by
    overlap with brute force over the decoded codes); the short list is exactly the F x k of
    those nearest by their fp16 codes on the first d; the rows that come back are among it
    and ranked by their fp16 codes on all D dimensions."""
    faiss = faiss_module()
    x = _rows(n=3000, noise=0.3)
    q = _rows(n=15, noise=0.3, seed=13)
    k = 5
    dist, ids, y, qy, scan, _index = _short_list_search("PCA32:16,SQfp16,FS8x3,k4", x, q, k)
    front = faiss.downcast_index(scan.base_index)
    pq = faiss.downcast_index(front.index)
    assert isinstance(pq, faiss.IndexPQFastScan) and (pq.d, pq.M, pq.nbits) == (16, 8, 4)
    decoded = np.stack([pq.reconstruct(i) for i in range(pq.ntotal)])
    size = 3 * 4 * k
    _, in_front = front.search(qy, size)
    want = _brute(decoded, qy[:, :16], size)
    shared = [len(np.intersect1d(a, b)) / size for a, b in zip(in_front, want, strict=True)]
    assert np.mean(shared) >= 0.9
    _, short_list = scan.search(qy, 4 * k)
    y16 = y[:, :16].astype(np.float16).astype(np.float32)
    for j in range(len(q)):
        order = np.argsort(((y16[in_front[j]] - qy[j, :16]) ** 2).sum(1), kind="stable")
        assert set(short_list[j]) == set(in_front[j][order[: 4 * k]])
        assert set(ids[j]) <= set(short_list[j])
    _assert_ranked_by_fp16_codes(dist, ids, y, qy)


def test_fast_scan_in_front_changes_nothing_when_its_list_covers_the_map(tmp_path):
    """With G x F x k >= N every row reaches the short scan: the plain scan's answers, also
    after a write and a memory-mapped read; G is a search parameter, and with a list of 4 x
    8 x 10 of 4000 rank-24 rows the fast scan keeps at least 97 % of the exact top 10, fewer
    with G = 1."""
    _front_covering_the_map("FS3x100", 14, tmp_path)
    index, path, hits = _low_rank_hits("PCA32:16,SQfp16,FS8x4,k8", tmp_path, 15)
    assert hits(index) >= 0.97
    assert hits(read_faiss(path, mmap=True)) == hits(index)
    assert hits(read_faiss(path, "k_factor_front=1")) < hits(index)


@pytest.mark.parametrize(
    ("factory", "params", "match"),
    [
        ("PCA32:8,SQfp16,k4", "k_factor_front=2", "a scan in front"),
        ("PCA32:8,SQfp16,HNSW8", "k_factor_front=2", "a scan in front"),
        ("PCA32:8,SQfp16,S4", "k_factor_front=0.5", "a number >= 1"),
        ("PCA32:8,SQfp16,S4", "k_factor_front=two", "a number >= 1"),
        ("PCA32:8,SQfp16,S4", "k_factor_front=2,no_such=3", "could not set parameter no_such"),
    ],
)
def test_bad_front_factors_are_errors(factory, params, match):
    index, _ = build_faiss(_rows(n=300, d=48), L2, factory)
    with pytest.raises(IndexBuildError, match=match):
        set_search_params(index, params)
