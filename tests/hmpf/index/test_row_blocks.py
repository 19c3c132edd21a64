"""Arrays given block by block (:class:`~hmpf.index.storage.RowBlocks`) are written exactly
as the whole arrays are: the same datasets, dtypes and bytes, whatever the block size."""

from __future__ import annotations

import numpy as np
import pytest

from hmpf.index.storage import RowBlocks, open_h5, write_local, write_references
from hmpf.index.tables import Ragged, RefTable
from hmpf.methods import create_method


def _blocks(x: np.ndarray, block_rows: int) -> RowBlocks:
    return RowBlocks(x.shape, x.dtype, lambda a, b: x[a:b], block_rows=block_rows)


@pytest.mark.parametrize("block_rows", [1, 3, 7, 1000])
@pytest.mark.parametrize("precision", ["exact", "compact"])
def test_references_from_blocks_equal_references_from_arrays(tmp_path, block_rows, precision):
    rng = np.random.default_rng(0)
    n = 23
    refs = RefTable([f"r{i}" for i in range(n)], ["0" * 64] * n)
    methods = {"gem": create_method("gem"), "gist": create_method("gist")}
    mats = {
        "gem": rng.random((n, 16), dtype=np.float32),
        "gist": rng.random((n, 8)).astype(np.float16).astype(np.float32),  # lossless half
    }
    a, b = tmp_path / "arrays.h5", tmp_path / "blocks.h5"
    sizes_a = write_references(a, refs, mats, methods, precision)
    blocks = {m: _blocks(x, block_rows) for m, x in mats.items()}
    sizes_b = write_references(b, refs, blocks, methods, precision)
    assert sizes_a == sizes_b
    with open_h5(a) as fa, open_h5(b) as fb:
        for m in mats:
            da, db = fa["global"][m], fb["global"][m]
            assert da.dtype == db.dtype and da.chunks is None and db.chunks is None
            assert dict(da.attrs) == dict(db.attrs)
            assert np.array_equal(da[()], db[()])


def test_local_blocks_equal_the_equal_count_layout(tmp_path):
    rng = np.random.default_rng(1)
    n, per = 9, 4
    regions = rng.random((n * per, 5), dtype=np.float32)
    methods = {"olo": create_method("olo")}
    rag = Ragged(regions, np.arange(0, n * per + 1, per, dtype=np.int64))
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    write_local(a, {"olo": {"regions": rag}}, methods, "exact")
    whole = regions.reshape(n, per, 5)
    write_local(b, {"olo": {"regions": _blocks(whole, 2)}}, methods, "exact")
    with open_h5(a) as fa, open_h5(b) as fb:
        ga, gb = fa["local"]["olo"]["regions"], fb["local"]["olo"]["regions"]
        assert list(ga) == list(gb) == ["blocks"]
        assert np.array_equal(ga["blocks"][()], gb["blocks"][()])
        assert dict(ga.attrs) == dict(gb.attrs)


def test_take_and_blocks_read_the_rows_asked_for():
    x = np.arange(50, dtype=np.float32).reshape(25, 2)
    rb = _blocks(x, 4)
    assert np.array_equal(np.concatenate([blk for _, blk in rb.blocks()]), x)
    assert [s for s, _ in rb.blocks()] == list(range(0, 25, 4))
    idx = np.array([0, 3, 4, 17, 24])
    assert np.array_equal(rb.take(idx), x[idx])
    bad = RowBlocks((5, 2), np.float32, lambda a, b: np.zeros((b - a, 3)))
    with pytest.raises(ValueError, match="expected"):
        bad.rows(0, 2)


@pytest.mark.parametrize(("factory", "params"), [("Flat", ""), ("IVF4,Flat", "nprobe=4")])
def test_faiss_from_blocks_holds_every_row_as_from_the_array(factory, params, monkeypatch):
    """Trained on a sample, filled block by block: every row found as itself, and with a
    whole-array training set (sample >= N) the same index as from the array."""
    import indexer.build as B
    from hmpf.index.ann import build_faiss, declared_metric

    rng = np.random.default_rng(2)
    x = rng.random((300, 12), dtype=np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    metric = declared_metric("gem", create_method("gem"))
    got, _ = B._faiss_from_blocks(_blocks(x, 64), metric, factory, params)
    want, _ = build_faiss(x, metric, factory, params)
    assert got.ntotal == want.ntotal == 300
    _, ig = got.search(x[:20], 5)
    _, iw = want.search(x[:20], 5)
    assert np.array_equal(ig, iw)
    monkeypatch.setattr(B, "FAISS_TRAIN_ROWS", 100)  # trained on a third of the rows
    small, _ = B._faiss_from_blocks(_blocks(x, 64), metric, factory, params)
    _, own = small.search(x, 1)
    assert small.ntotal == 300 and (own[:, 0] == np.arange(300)).mean() >= 0.95
