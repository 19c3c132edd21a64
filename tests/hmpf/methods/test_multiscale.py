"""Multi-scale and multi-crop pooling of the CNN global descriptors (issue 18).

``scales`` (GeM, NetVLAD) against the single-scale methods run at each scaled input size,
``crops`` (GeM) against a per-region loop, the region grid by hand, keys (unchanged at the
defaults), forward-pass groups, config errors, and both options through a real index build
and reload (HDF5, FAISS).
"""

from __future__ import annotations

import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.errors import ConfigError
from hmpf.index import IndexReader
from hmpf.methods import create_method
from hmpf.methods.base import euclidean, fit_many, method_groups
from hmpf.methods.cnn import forward_group, l2_rows, scaled_size
from hmpf.methods.gem import crop_boxes
from hmpf.methods.netvlad import vlad
from indexer.build import BuildOptions, build
from tests.conftest import synthetic_image, write_synthetic_images

pytest.importorskip("torch")

#: Small inputs keep the ONNX exports and forward passes of these tests cheap.
SMALL = [96, 96]


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_scaled_sizes():
    assert scaled_size((224, 224), 1.0) == (224, 224)
    assert scaled_size((230, 250), 1.0) == (230, 250)  # scale 1 is the size itself
    assert scaled_size((224, 224), 1.5) == (352, 352)  # 10.5 cells round up
    assert scaled_size((288, 512), 0.75) == (224, 384)
    assert scaled_size((96, 96), 0.25) == (32, 32)  # at least one cell
    gem = create_method("gem", {"input_size": SMALL, "scales": [1.0, 1.5, 0.5]})
    assert gem.input_sizes() == [(96, 96), (160, 160), (64, 64)]


def test_crop_boxes_by_hand():
    assert crop_boxes(7, 7, 0) == [(0, 0, 7, 7)]
    # Level 1 of a square map is the map itself (dropped as a duplicate); level 2: four
    # 5 x 5 squares overlapping by 3.
    assert crop_boxes(7, 7, 2) == [
        (0, 0, 7, 7),
        (0, 0, 5, 5),
        (0, 2, 5, 7),
        (2, 0, 7, 5),
        (2, 2, 7, 7),
    ]
    # 9 x 16: level 1 is three 9 x 9 squares along the long axis.
    assert crop_boxes(9, 16, 1) == [(0, 0, 9, 16), (0, 0, 9, 9), (0, 4, 9, 13), (0, 7, 9, 16)]
    for h, w, levels in ((7, 7, 3), (9, 16, 3), (2, 3, 4), (1, 1, 2)):
        boxes = crop_boxes(h, w, levels)
        assert len(set(boxes)) == len(boxes)
        for y0, x0, y1, x1 in boxes:
            assert 0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w


@pytest.mark.parametrize("crops", [1, 2, 3])
def test_gem_crops_match_a_per_region_loop(crops):
    rng = np.random.default_rng(crops)
    a = rng.gamma(2.0, size=(16, 7, 9)).astype(np.float32)
    a[:, 2, 3] = 0.0  # clamped to eps like the whole-map GeM
    gem = create_method("gem", {"crops": crops})
    got = gem.from_maps({gem.layers()[0]: a})
    total = np.zeros(16)
    for y0, x0, y1, x1 in crop_boxes(7, 9, crops):
        region = np.maximum(a[:, y0:y1, x0:x1].astype(np.float64), 1e-6)
        total += _unit(np.array([np.mean(c**3) ** (1 / 3) for c in region]))
    assert got.dtype == np.float32
    assert np.allclose(got, _unit(total), atol=1e-3)
    plain = create_method("gem").from_maps({gem.layers()[0]: a})
    assert not np.allclose(got, plain, atol=1e-3)  # the crops change the descriptor
    whole = create_method("gem", {"crops": 0}).from_maps({gem.layers()[0]: a})
    assert np.array_equal(whole, plain)


def test_multiscale_gem_is_the_mean_of_single_scale_descriptors():
    scales = [1.0, 1.5]
    multi = create_method("gem", {"input_size": SMALL, "scales": scales})
    singles = [create_method("gem", {"input_size": list(s)}) for s in multi.input_sizes()]
    for seed in (0, 1):
        image = synthetic_image(seed)
        got = multi.extract(image)
        per = [_unit(m.extract(image)) for m in singles]
        assert np.allclose(got, _unit(np.mean(per, axis=0)), atol=2e-3)
        assert not np.allclose(got, per[0], atol=2e-3)
    # Crops and scales combine: the mean over scales of the multi-crop descriptors.
    both = create_method("gem", {"input_size": SMALL, "scales": scales, "crops": 1})
    crop_singles = [
        create_method("gem", {"input_size": list(s), "crops": 1}) for s in both.input_sizes()
    ]
    image = synthetic_image(2)
    per = [_unit(m.extract(image)) for m in crop_singles]
    assert np.allclose(both.extract(image), _unit(np.mean(per, axis=0)), atol=2e-3)


def test_multiscale_netvlad_pools_the_local_features_of_every_scale():
    params = {"clusters": 4, "input_size": SMALL, "scales": [1.0, 0.5]}
    multi = create_method("netvlad", params)
    images = [synthetic_image(i) for i in range(4)]
    fit_many({"nv": multi}, images)
    c, assign, bias = multi._params()
    singles = [
        create_method("netvlad", {"clusters": 4, "input_size": list(s)})
        for s in multi.input_sizes()
    ]
    layer = multi.layers()[0]
    for image in images[:2]:
        local = []
        for m in singles:
            (maps,) = forward_group([m], [image])
            a = maps[layer]
            local.append(l2_rows(a.reshape(a.shape[0], -1).T))
        x = np.concatenate(local)
        assert len(x) == 3 * 3 + 2 * 2  # 96 px -> 3 x 3 cells, 64 px -> 2 x 2
        assert np.allclose(multi.extract(image), vlad(x, c, assign, bias), atol=2e-3)


def test_keys_are_unchanged_at_the_defaults():
    # The keys these methods had before the options existed (cached descriptors and index
    # identities stay valid): computed on commit a3261cd.
    assert create_method("gem").cache_key() == "gem-aaf412d6e86b63da"
    assert create_method("netvlad").cache_key() == "netvlad-4679ff288cee5588"
    assert create_method("netvlad", {"clusters": 32}).cache_key() == "netvlad-69c856db582935fa"
    explicit = create_method("gem", {"scales": [1.0], "crops": 0})
    assert explicit.cache_key() == "gem-aaf412d6e86b63da"
    keys = {
        create_method("gem", p).descriptor_key()
        for p in ({}, {"scales": [1.0, 1.5]}, {"scales": [1.5, 1.0]}, {"crops": 2})
    }
    assert len(keys) == 4
    nv = create_method("netvlad", {"scales": [1.0, 0.75]})
    assert nv.cache_key() != create_method("netvlad").cache_key()


def test_scales_split_the_forward_pass_groups():
    methods = {
        "gem": create_method("gem", {"input_size": SMALL}),
        "gem_ms": create_method("gem", {"input_size": SMALL, "scales": [1.0, 0.5]}),
        "gem_ms_crops": create_method(
            "gem", {"input_size": SMALL, "scales": [1.0, 0.5], "crops": 2}
        ),
        "nv": create_method("netvlad", {"input_size": SMALL}),
    }
    groups = [sorted(g) for g in method_groups(methods)]
    assert sorted(groups) == [["gem", "nv"], ["gem_ms", "gem_ms_crops"]]


@pytest.mark.parametrize(
    "name,params,match",
    [
        ("gem", {"scales": []}, "scales"),
        ("gem", {"scales": [1.0, 0.1]}, "scale"),
        ("gem", {"scales": [1.0, 5.0]}, "scale"),
        ("netvlad", {"scales": [1.0, 1.0]}, "distinct"),
        ("netvlad", {"scales": [1.0, 0.5, 0.75, 1.25, 1.5]}, "scales"),
        ("gem", {"crops": 5}, "crops"),
        ("gem", {"crops": -1}, "crops"),
        ("netvlad", {"crops": 1}, "crops"),  # multi-crop is GeM's
        ("olo", {"scales": [1.0, 0.5]}, "scales"),  # OLO is single-scale
    ],
)
def test_bad_values_are_config_errors(name, params, match):
    with pytest.raises(ConfigError, match=match):
        create_method(name, params)


def test_multiscale_and_crops_through_an_index(tmp_path):
    cfg = parse_config(
        {
            "methods": {
                "gem": {"input_size": SMALL, "scales": [1.0, 0.5], "crops": 1},
                "netvlad": {"clusters": 4, "input_size": SMALL, "scales": [1.0, 1.5]},
            },
            "tiers": [{"methods": ["gem", "netvlad"], "k": 1}],
        }
    )
    folder = write_synthetic_images(tmp_path / "a", 6)
    build(cfg, folder, tmp_path / "index", options=BuildOptions(workers=1, progress=False))
    images = [synthetic_image(i) for i in range(6)]
    with IndexReader(tmp_path / "index") as r:
        for mid in ("gem", "netvlad"):
            m = r.methods[mid]
            assert list(m.config.scales) == cfg.methods[mid]["scales"]  # type: ignore[attr-defined]
            own = np.stack([m.extract(im) for im in images])  # a query's descriptors
            assert np.allclose(r.global_matrix(mid), own, atol=1e-3)
            ids, raw = r.search(mid, own[4], 2)
            brute = euclidean(own[4][None], r.global_matrix(mid))[0]
            assert ids[0] == 4 == int(brute.argmin())
            assert np.allclose(raw, np.sort(brute)[:2], atol=1e-3)
