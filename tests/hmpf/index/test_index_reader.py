"""Index format and reader: equality with in-memory evaluation, FAISS vs brute force,
corruption detected on open, float16 policy."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from hmpf.config import build_methods, parse_config
from hmpf.features import extract_images
from hmpf.hierarchy import Hierarchy, feature_scorer
from hmpf.imageio import load_image
from hmpf.index import IndexCorruptError, IndexReader, IndexVersionError, layout
from hmpf.index.storage import storage_dtype
from hmpf.index.tables import Ragged
from hmpf.methods import create_method
from indexer.build import BuildOptions, build

CONFIG = {
    "name": "index-test",
    "methods": {"kaze": {"max_keypoints": 60}},
    "tiers": [
        {"methods": ["hog", "gist"], "k": 5},
        {"methods": ["gist", "sad", "kaze"], "k": 1},
    ],
}
OPTS = BuildOptions(workers=1, progress=False)


@pytest.fixture(scope="module")
def gp_subset(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """The first 12 Gardens Point day_right images (references) and 4 night_right queries."""
    from hmpf.datasets import dataset_root

    root = dataset_root() / "gardens_point"
    if not (root / "day_right").is_dir():
        pytest.skip(f"Gardens Point not found under {root}")
    folder = tmp_path_factory.mktemp("gp") / "refs"
    folder.mkdir()
    for p in sorted((root / "day_right").iterdir())[:12]:
        shutil.copy(p, folder / p.name)
    queries = sorted((root / "night_right").iterdir())[:4]
    return folder, queries


@pytest.fixture(scope="module")
def built(gp_subset, tmp_path_factory) -> Path:
    index = tmp_path_factory.mktemp("index") / "gp"
    build(parse_config(CONFIG), gp_subset[0], index, options=OPTS)
    return index


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


def test_hierarchy_over_index_equals_in_memory(gp_subset, built):
    refs_dir, queries = gp_subset
    config = parse_config(CONFIG)
    methods = build_methods(config)
    refs = sorted(refs_dir.iterdir())
    ref = extract_images(refs, methods, workers=1)
    qry = extract_images(queries, methods, workers=1)
    db = {m: methods[m].stack(ref.features[m]) for m in methods}
    hier = Hierarchy(config, methods)
    with IndexReader(built, expected_config=config) as reader:
        assert reader.refs.names == [p.name for p in refs]
        ihier = reader.hierarchy()
        for qi in range(len(queries)):
            q = {m: qry.features[m][qi] for m in methods}
            a = hier.run(feature_scorer(methods, q, db), len(refs))
            b = ihier.run(reader.scorer(reader.extract_query(load_image(queries[qi]))), reader.n)
            assert (a.match, a.quality) == (b.match, b.quality) or (
                a.match == b.match and np.isnan(a.quality) and np.isnan(b.quality)
            )
            assert _same(a.combined, b.combined)
            assert _same(a.final_candidates, b.final_candidates)
            for ta, tb in zip(a.tiers, b.tiers, strict=True):
                assert _same(ta.candidates, tb.candidates)
                for m in ta.scores:
                    assert _same(ta.scores[m], tb.scores[m])


def test_stored_features_roundtrip(gp_subset, built):
    methods = build_methods(parse_config(CONFIG))
    refs = sorted(gp_subset[0].iterdir())
    ref = extract_images(refs[:3], methods, workers=1)
    with IndexReader(built) as reader:
        for mid in ("hog", "gist", "sad"):
            assert reader.global_matrix(mid).dtype == ref.features[mid][0].dtype
            assert np.array_equal(reader.global_matrix(mid)[:3], np.stack(ref.features[mid]))
        got = reader.local_features("kaze", np.array([2, 0]))
        for g, want in zip(got, [ref.features["kaze"][2], ref.features["kaze"][0]], strict=True):
            assert np.array_equal(g.descriptors, want.descriptors)
            assert np.array_equal(g.keypoints, want.keypoints)


def test_faiss_flat_equals_brute_force(built):
    with IndexReader(built) as reader:
        for mid in ("hog", "gist"):
            method = reader.methods[mid]
            matrix = reader.global_matrix(mid)
            for qi in (0, 5):
                ids, raw = reader.search(mid, matrix[qi], 6)
                brute = method.scores(matrix[qi], matrix)
                order = np.argsort(brute, kind="stable")[:6]
                assert list(ids) == list(order)
                np.testing.assert_allclose(raw, brute[order], rtol=1e-4, atol=1e-3)


def test_storage_dtype_policy():
    hog = create_method("hog")
    exact = np.array([0.5, 0.25, 1.0], np.float32)
    lossy = np.array([0.1, 0.2], np.float32)
    assert storage_dtype(hog, exact, "exact") == np.float16
    assert storage_dtype(hog, lossy, "exact") == np.float32
    assert storage_dtype(hog, lossy, "compact") == np.float16
    assert storage_dtype(hog, np.array([1e6], np.float32), "compact") == np.float32
    assert storage_dtype(hog, np.array([3], np.uint8), "compact") == np.uint8


def test_ragged_select_and_concat():
    items = [np.arange(n * 2).reshape(n, 2) for n in (3, 0, 2)]
    r = Ragged.from_items(items)
    s = r.select(np.array([2, 0]))
    assert np.array_equal(s.item(0), items[2]) and np.array_equal(s.item(1), items[0])
    c = Ragged.concat([r, s])
    assert len(c) == 5 and np.array_equal(c.item(4), items[0]) and c.item(1).shape == (0, 2)


def _copy(built: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(built, dst)
    return dst


def test_reader_rejects_truncated_hdf5(built, tmp_path):
    idx = _copy(built, tmp_path)
    f = idx / "v0001" / "local.h5"
    f.write_bytes(f.read_bytes()[:1000])
    with pytest.raises(IndexCorruptError, match="local.h5"):
        IndexReader(idx)


def test_reader_rejects_other_format_major_and_config(built, tmp_path):
    import json

    idx = _copy(built, tmp_path)
    m = idx / "v0001" / "manifest.json"
    data = json.loads(m.read_text())
    other = parse_config({**CONFIG, "name": "other"})
    with pytest.raises(IndexVersionError, match="expected 'other'"):
        IndexReader(idx, expected_config=other)
    data["config"]["resolved"]["tiers"][0]["k"] = 7
    layout.write_manifest(m.parent, data)  # as hmpf writes it (sealed)
    with pytest.raises(IndexCorruptError, match="config hash"):
        IndexReader(idx)
    data["format_version"] = "2.0"
    layout.write_manifest(m.parent, data)  # as hmpf writes it (sealed)
    with pytest.raises(IndexVersionError, match="rebuild"):
        IndexReader(idx)


def test_reader_checks_the_build_package_versions(built, tmp_path, caplog):
    import json
    import logging

    import cv2

    idx = _copy(built, tmp_path)
    m = idx / "v0001" / "manifest.json"
    data = json.loads(m.read_text())
    packages = data["packages"]
    from hmpf.index.layout import OPENCV_DISTS, installed_version

    (cv,) = [d for d in OPENCV_DISTS if d in packages]  # the OpenCV wheel installed here
    assert packages[cv].split(".")[0] == cv2.__version__.split(".")[0]
    major, minor, *_ = packages[cv].split(".")
    # Another minor version of OpenCV (or another numpy): opened, with a warning.
    packages[cv] = f"{major}.{int(minor) + 1}.0"
    packages["numpy"] = "1.0.0"
    layout.write_manifest(m.parent, data)  # as hmpf writes it (sealed)
    with caplog.at_level(logging.WARNING, logger="hmpf.index"):
        IndexReader(idx).close()
    assert cv in caplog.text and "numpy 1.0.0" in caplog.text
    # Another major version of OpenCV: the stored HOG/Gist/KAZE are not comparable.
    packages[cv] = f"{int(major) + 1}.0.0"
    layout.write_manifest(m.parent, data)  # as hmpf writes it (sealed)
    with pytest.raises(IndexVersionError, match=rf"{cv}==\d"):
        IndexReader(idx)
    # An index built with the other OpenCV wheel of the same version opens without a note.
    other = next(d for d in OPENCV_DISTS if d != cv)
    del packages[cv]
    packages[other] = installed_version(cv)
    packages["numpy"] = np.__version__
    layout.write_manifest(m.parent, data)  # as hmpf writes it (sealed)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hmpf.index"):
        IndexReader(idx).close()
    assert "opencv" not in caplog.text


def test_reader_rejects_wrong_shapes(built, tmp_path):
    import h5py

    idx = _copy(built, tmp_path)
    with h5py.File(idx / "v0001" / "references.h5", "a") as f:
        del f["global/gist"]
        f.create_dataset("global/gist", data=np.zeros((3, 512), np.float32))
        f["global/gist"].attrs["dtype"] = "<f4"
    with pytest.raises(IndexCorruptError, match="references.h5: .*manifest"):
        IndexReader(idx)  # the checksums see it first
    with pytest.raises(IndexCorruptError, match="global/gist has shape"):
        IndexReader(idx, verify=False)  # and the shapes behind them


def test_hmpf_eval_index(gp_subset, built, tmp_path, capsys):
    from hmpf.cli.eval import main as eval_main

    queries = tmp_path / "q"
    queries.mkdir()
    for p in gp_subset[1]:
        shutil.copy(p, queries / p.name)
    out = tmp_path / "r.json"
    args = ["--index", str(built), "--query", str(queries), "--no-cache", "--quiet"]
    assert eval_main([*args, "--workers", "1", "--json", str(out)]) == 0
    assert "Combined recall@1" in capsys.readouterr().out
    rep = json.loads(out.read_text())
    assert len(rep["hierarchy"]["matches"]) == 4
    # The index's config has no confidence model: no made-up probability; the quality rule
    # decides, as in the service (one policy, hmpf.acceptance).
    single = rep["acceptance"]["single"]
    assert single["p_correct"] == [None] * 4 and single["rule"] == "quality"
    assert len(single["accepted_answers"]) == 4
