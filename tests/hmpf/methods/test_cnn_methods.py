"""CNN methods: hand-built cases for the descriptor rules, slow references for the vectorised
paths, and shape / determinism / fitted-state tests on the bundled EfficientNet-Lite0."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from hmpf.config import build_methods, parse_config
from hmpf.features import FeatureCache, extract_images, file_digest, fit_methods
from hmpf.methods import create_method
from hmpf.methods.base import extract_many, fit_many
from hmpf.methods.cnn import cluster_sums, kmeans, l2_rows, nearest
from hmpf.methods.hybridnet import max_location_histogram
from hmpf.methods.netvlad import vlad
from hmpf.methods.olo import OloFeatures, encode_regions, olo_similarity

torch = pytest.importorskip("torch")


# ---------------------------------------------------------------------------------- HybridNet


def test_hybridnet_histogram_hand_built_with_ties() -> None:
    a = np.zeros((5, 13, 13), dtype=np.float32)
    a[0, 2, 5] = 3.0  # single max at row 2, col 5 -> index 5 + 13 * (12 - 2) = 135
    # Ties: (row 4, col 3), (row 1, col 7), (row 9, col 3): MATLAB takes the first in
    # column-major order: smallest column (3), then smallest row (4) -> 3 + 13 * 8 = 107.
    a[1, 4, 3] = a[1, 1, 7] = a[1, 9, 3] = 2.0
    # channel 2: all zero -> skipped; channel 3: max is 0 (negatives elsewhere) -> skipped.
    a[3] = -1.0
    a[3, 0, 0] = 0.0
    # channel 4: all equal and positive -> first location (row 0, col 0) -> 0 + 13 * 12.
    a[4] = 0.5
    h = max_location_histogram(a)
    assert h.shape == (169,) and h.dtype == np.float32
    expected = np.zeros(169)
    expected[[135, 107, 156]] = 1
    np.testing.assert_array_equal(h, expected)
    with pytest.raises(ValueError, match="13x13"):
        max_location_histogram(np.zeros((2, 14, 14)))


# -------------------------------------------------------------------------------------- OLO


def _slow_olo(t: np.ndarray, q: np.ndarray, wt: np.ndarray, wq: np.ndarray, idf: np.ndarray):
    """compare_two as written (spec §2.4, docs/spec/olo.md), with loops."""
    s = t @ q.T
    total = 0.0
    for i in range(len(t)):
        j = int(np.argmax(s[i]))
        if int(np.argmax(s[:, j])) == i and s[i, j] != 0:
            total += s[i, j] * idf[wt[i]] * idf[wq[j]]
    return total / len(t)


def test_olo_similarity_hand_built_pair() -> None:
    e = np.eye(4, dtype=np.float32)
    # Reference regions: e0, e1, (e0 + e2)/sqrt2, e3. Query regions: e0, e2, e1.
    t = np.stack([e[0], e[1], (e[0] + e[2]) / np.sqrt(2), e[3]])
    q = np.stack([e[0], e[2], e[1]])
    wt, wq = np.array([0, 1, 2, 3]), np.array([0, 2, 1])
    idf = np.array([1.0, 2.0, 0.5, 3.0])
    # Mutual: t0<->q0 (1.0, idf 1*1), t1<->q2 (1.0, idf 2*2), t2 -> q0? s[2] = [.707, .707, 0]:
    # argmax q0 (first), but q0's best is t0 -> not mutual. t3: all zero -> no match.
    expected = (1.0 * 1 * 1 + 1.0 * 2 * 2) / 4
    got = olo_similarity(t[None], wt[None], np.array([4]), q, wq, idf)
    np.testing.assert_allclose(got, [expected], rtol=1e-6)
    assert _slow_olo(t, q, wt, wq, idf) == pytest.approx(expected)


def test_olo_similarity_vectorised_equals_loops_with_padding() -> None:
    rng = np.random.default_rng(3)
    idf = rng.uniform(0.1, 3.0, 50)
    q = l2_rows(np.abs(rng.standard_normal((30, 16))))
    wq = rng.integers(0, 50, 30)
    sets, counts = [], []
    for n in (25, 40, 1, 33):
        sets.append(l2_rows(np.abs(rng.standard_normal((n, 16)))))
        counts.append(n)
    refs = np.zeros((4, 40, 16), np.float32)
    words = np.zeros((4, 40), np.int64)
    for i, (s, n) in enumerate(zip(sets, counts, strict=True)):
        refs[i, :n] = s
        words[i, :n] = rng.integers(0, 50, n)
    got = olo_similarity(refs, words, np.array(counts), q, wq, idf)
    want = [_slow_olo(sets[i], q, words[i, : counts[i]], wq, idf) for i in range(4)]
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_olo_encode_regions_order_bbox_and_ties() -> None:
    mask = np.zeros((2, 6, 6), dtype=np.float32)
    # Channel 0: component A at rows 3-4, col 1 (first in column-major scan), component B
    # an L shape at (0,4), (1,4), (1,5) with bbox rows 0-1, cols 4-5.
    mask[0, 3, 1], mask[0, 4, 1] = 1.0, 3.0
    mask[0, 0, 4], mask[0, 1, 4], mask[0, 1, 5] = 2.0, 2.0, 2.0
    # Channel 1: one pixel, mean 2.0 (ties with B).
    mask[1, 5, 5] = 2.0
    feat = np.zeros((3, 6, 6), dtype=np.float32)
    feat[0] = 1.0
    feat[1, 0, 5] = 4.0  # inside B's bbox but not in the component: pooled anyway
    feat[2, 4, 1] = 1.0
    regions = encode_regions(feat, mask, n_regions=2)
    # Means: A 2.0, B 2.0, C 2.0 -> the 2nd largest is 2.0, ties keep all three, in order.
    assert regions.shape == (3, 3)
    # A: P = [1, 3]/sqrt(10) (column-major), F rows: [1, 1], [0, 0], [0, 1].
    pa = np.array([1.0, 3.0]) / np.sqrt(10)
    va = np.array([pa.sum(), 0.0, pa[1]])
    np.testing.assert_allclose(regions[0], va / np.linalg.norm(va), rtol=1e-6)
    # B: bbox rows 0-1, cols 4-5; column-major P = [m(0,4), m(1,4), m(0,5), m(1,5)].
    pb = np.array([2.0, 2.0, 0.0, 2.0])
    pb = pb / np.linalg.norm(pb)
    vb = np.array([pb.sum(), 4.0 * pb[2], 0.0])
    np.testing.assert_allclose(regions[1], vb / np.linalg.norm(vb), rtol=1e-6)
    np.testing.assert_allclose(regions[2], [1.0, 0.0, 0.0], rtol=1e-6)
    # n_regions=1: the threshold is still 2.0 and all three tie.
    assert encode_regions(feat, mask, n_regions=1).shape == (3, 3)
    mask[0, 4, 1] = 5.0  # A's mean becomes 3.0: the only region >= the 1st largest
    assert encode_regions(feat, mask, n_regions=1).shape == (1, 3)
    assert encode_regions(feat, np.zeros_like(mask)).shape == (0, 3)


# ---------------------------------------------------------------------------------- NetVLAD


def test_vlad_equals_loop_reference() -> None:
    rng = np.random.default_rng(0)
    n, d, k = 37, 8, 5
    x = l2_rows(rng.standard_normal((n, d)))
    c = rng.standard_normal((k, d)).astype(np.float32)
    w = rng.standard_normal((d, k)).astype(np.float32)
    b = rng.standard_normal(k).astype(np.float32)
    got = vlad(x, c, w, b)
    v = np.zeros((k, d))
    for i in range(n):
        logit = x[i] @ w + b
        a = np.exp(logit - logit.max())
        a /= a.sum()
        for j in range(k):
            v[j] += a[j] * (x[i] - c[j])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    flat = np.array([v[j, dd] for dd in range(d) for j in range(k)])  # k fastest
    flat /= np.linalg.norm(flat)
    np.testing.assert_allclose(got, flat, rtol=1e-4, atol=1e-6)
    assert got.shape == (k * d,)


def test_kmeans_deterministic_and_separates_clusters() -> None:
    rng = np.random.default_rng(1)
    centres = np.array([[0, 0], [10, 0], [0, 10]], np.float32)
    x = np.concatenate([c + rng.normal(0, 0.3, (100, 2)) for c in centres]).astype(np.float32)
    a, b = kmeans(x, 3, seed=4), kmeans(x, 3, seed=4)
    np.testing.assert_array_equal(a, b)
    assert sorted(np.round(a).astype(int).tolist()) == sorted(centres.astype(int).tolist())
    assert nearest(np.array([[9.0, 1.0]]), a).item() == int(np.argmin(np.abs(a - [10, 0]).sum(1)))
    assert kmeans(np.ones((5, 2)), 3).shape == (1, 2)  # fewer distinct points than k


@pytest.mark.parametrize(("n", "k"), [(0, 3), (1, 1), (500, 7), (3000, 64)])
def test_cluster_sums_equal_add_at_to_the_bit(n: int, k: int) -> None:
    """k-means' per-cluster sums (sort + reduceat) against ``np.add.at``, the brute force:
    empty clusters, one point, more clusters than used labels."""
    rng = np.random.default_rng(n)
    x = rng.normal(0, 3, (n, 16))
    assign = rng.integers(0, max(1, k - 2), n)  # the last clusters stay empty
    expect = np.zeros((k, 16))
    np.add.at(expect, assign, x)
    np.testing.assert_allclose(cluster_sums(x, assign, k), expect, rtol=1e-12, atol=1e-12)
    # k-means' points are float32: these float64 sums are exact, in any order.
    x32 = x.astype(np.float32)
    expect = np.zeros((k, 16))
    np.add.at(expect, assign, x32)
    np.testing.assert_array_equal(cluster_sums(x32.astype(np.float64), assign, k), expect)


def test_published_netvlad_pipeline_on_synthetic_pitts30k(tmp_path: Path) -> None:
    from tests.hmpf.methods.test_backbones_weights import _pitts_layers, _save_pitts

    path = tmp_path / "Pitts30K_struct.mat"
    layers, head = _pitts_layers(np.random.default_rng(0))
    _save_pitts(path, layers)
    nv = create_method("netvlad", {"backbone": "vgg16", "weights": str(path)})
    assert not nv.requires_fit()
    img = np.random.default_rng(2).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    f = nv.extract(img)
    assert f.shape == (head["wpca_b"].shape[0],)
    assert float(np.linalg.norm(f)) == pytest.approx(1.0, abs=1e-5)
    # The same pipeline by hand from conv5_3: preL2, VLAD (no bias), intra, L2, WPCA, L2.
    net = nv.backbone()
    x = net.preprocess(img, (224, 224))
    with torch.inference_mode():
        conv = net.forward_maps(torch.from_numpy(x[None]), ["conv5_3"])["conv5_3"][0].numpy()
    local = l2_rows(conv.reshape(512, -1).T)
    p = net.netvlad_params()
    v = vlad(local, -head["neg_centroids"][0, 0].T, head["assign"][0, 0], None)
    y = v @ head["wpca"][0, 0] + head["wpca_b"]
    np.testing.assert_allclose(f, y / np.linalg.norm(y), rtol=1e-3, atol=1e-5)
    np.testing.assert_array_equal(p["centroids"], -head["neg_centroids"][0, 0].T)


# ---------------------------------------------------- every method on the bundled backbone


def _images(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        y, x = np.mgrid[0:180, 0:320]
        base = 128 + 80 * np.sin(x / rng.uniform(5, 30)) * np.cos(y / rng.uniform(5, 30))
        img = np.clip(base[..., None] + rng.normal(0, 25, (180, 320, 3)), 0, 255)
        out.append(img.astype(np.uint8))
    return out


def _image_files(folder: Path, n: int, seed: int) -> list[Path]:
    """``n`` of :func:`_images` written as PNG files in ``folder``."""
    import cv2

    paths = []
    for i, img in enumerate(_images(n, seed=seed)):
        p = folder / f"{i:03d}.png"
        cv2.imwrite(str(p), img[:, :, ::-1])
        paths.append(p)
    return paths


SMALL = {
    "gem": {"input_size": [96, 160]},
    "hybridnet": {"layer": "s5", "input_size": [208, 208]},
    "netvlad": {"input_size": [96, 160], "clusters": 8, "pca_dim": 4},
    "olo": {"vocabulary_size": 16, "regions": 50, "input_size": [160, 160]},
}


@pytest.fixture(scope="module")
def fitted() -> dict[str, object]:
    methods = {name: create_method(name, params) for name, params in SMALL.items()}
    fit_many(methods, _images(6))
    return methods


def test_methods_shapes_and_determinism(fitted: dict[str, object]) -> None:
    imgs = _images(3, seed=9)
    a = extract_many(fitted, imgs)  # type: ignore[arg-type]
    b = extract_many(fitted, imgs)  # type: ignore[arg-type]
    assert a["gem"][0].shape == (1280,)
    assert a["hybridnet"][0].shape == (169,) and a["hybridnet"][0].sum() > 0
    assert a["hybridnet"][0].sum() <= 112  # at most one vote per s5 channel
    assert a["netvlad"][0].shape == (4,)
    assert isinstance(a["olo"][0], OloFeatures)
    assert a["olo"][0].regions.shape[1] == 192 and 0 < len(a["olo"][0]) <= 60
    for name in SMALL:
        for fa, fb in zip(a[name], b[name], strict=True):
            if name == "olo":
                np.testing.assert_array_equal(fa.regions, fb.regions)
                np.testing.assert_array_equal(fa.words, fb.words)
            else:
                np.testing.assert_array_equal(fa, fb)
                assert np.linalg.norm(fa) > 0
    for name in ("gem", "netvlad"):
        assert float(np.linalg.norm(a[name][0])) == pytest.approx(1.0, abs=1e-3)  # float16
    # Batched extraction equals one image at a time.
    single = fitted["netvlad"].extract(imgs[1])  # type: ignore[attr-defined]
    np.testing.assert_allclose(single, a["netvlad"][1], rtol=1e-4, atol=1e-6)
    # A method scores itself best.
    olo = fitted["olo"]
    s = olo.scores(a["olo"][0], olo.stack(a["olo"]))  # type: ignore[attr-defined]
    assert int(np.argmax(s)) == 0


def test_fitted_state_round_trip_pickle_and_cache_key(fitted: dict[str, object]) -> None:
    img = _images(1, seed=4)
    for name in ("netvlad", "olo"):
        m = fitted[name]
        fresh = create_method(name, SMALL[name])
        assert fresh.requires_fit() and not m.requires_fit()  # type: ignore[attr-defined]
        assert fresh.cache_key() != m.cache_key()  # type: ignore[attr-defined]
        fresh.load_state(m.state_arrays())  # type: ignore[attr-defined]
        assert fresh.cache_key() == m.cache_key()  # type: ignore[attr-defined]
        clone = pickle.loads(pickle.dumps(m))
        fa, fb, fc = m.extract(img[0]), fresh.extract(img[0]), clone.extract(img[0])  # type: ignore[attr-defined]
        if name == "olo":
            fa, fb, fc = fa.regions, fb.regions, fc.regions
        np.testing.assert_array_equal(fa, fb)
        np.testing.assert_array_equal(fa, fc)
    with pytest.raises(RuntimeError, match="fit"):
        create_method("netvlad", SMALL["netvlad"]).extract(img[0])
    with pytest.raises(ValueError, match="lacks"):
        create_method("olo").load_state({"vocabulary": np.zeros((2, 80))})


def test_shared_forward_pass_per_group(monkeypatch: pytest.MonkeyPatch) -> None:
    # torch's forward_maps counted here; ONNX Runtime's runs in
    # tests/hmpf/methods/test_cnn_runtime.py
    monkeypatch.setattr("hmpf.runtime._cnn_runtime", "torch")
    gem = create_method("gem", {"input_size": [416, 416]})
    hyb = create_method("hybridnet")  # s6 at 416 x 416: same group as gem above
    other = create_method("gem", {"input_size": [96, 96]})
    net = gem.backbone()
    calls: list[tuple[int, tuple[str, ...]]] = []
    original = net.forward_maps

    def counting(batch, layers):  # type: ignore[no-untyped-def]
        calls.append((batch.shape[0], tuple(sorted(layers))))
        return original(batch, layers)

    net.forward_maps = counting  # type: ignore[method-assign]
    try:
        out = extract_many({"g": gem, "h": hyb, "o": other}, _images(3))
    finally:
        del net.forward_maps
    assert sorted(calls) == [(3, ("head",)), (3, ("head", "s6"))]
    assert len(out["g"]) == len(out["h"]) == len(out["o"]) == 3


def test_fit_methods_uses_cache(tmp_path: Path) -> None:
    paths = _image_files(tmp_path, 4, seed=2)
    cache = FeatureCache(tmp_path / "cache")
    cfg = parse_config(
        {"methods": {"netvlad": SMALL["netvlad"]}, "tiers": [{"methods": ["netvlad"], "k": 1}]}
    )
    first = build_methods(cfg)
    unfitted_key = first["netvlad"].descriptor_key()  # cache_key + the CNN runtime
    assert fit_methods(first, paths, cache=cache) == ["netvlad"]
    [stored] = list((tmp_path / "cache" / "fitted" / unfitted_key).glob("*.npz"))
    # Overwrite the stored state: a second fit on the same images must load it, not refit.
    state = first["netvlad"].state_arrays()
    state["centroids"] = state["centroids"] + 1.0
    cache.put_state(unfitted_key, stored.stem, state)
    second = build_methods(cfg)
    assert fit_methods(second, paths, cache=cache) == ["netvlad"]
    np.testing.assert_array_equal(second["netvlad"].state_arrays()["centroids"], state["centroids"])
    # Other images (by content) are another fitting set: fitted afresh.
    third = build_methods(cfg)
    fit_methods(third, paths[:3], cache=cache)
    np.testing.assert_raises(
        AssertionError,
        np.testing.assert_array_equal,
        third["netvlad"].state_arrays()["centroids"],
        state["centroids"],
    )


def test_fit_stores_the_references_features_extraction_would_compute(tmp_path: Path) -> None:
    """A fit computes the fitted methods' features of its images on the way (one forward pass
    per image, not two); with a cache they are stored, equal bit for bit to what extraction
    without a cache gives, so extracting those references reads them all."""
    paths = _image_files(tmp_path, 5, seed=4)
    cfg = parse_config(
        {
            "methods": {
                "netvlad": SMALL["netvlad"],
                "olo": SMALL["olo"],
                "gem": SMALL["gem"],
                "gist_w": {"type": "gist", "whiten": 16},  # a fitted non-CNN global method
                # fitted, sharing its forward pass with the unfitted gem
                "gem_w": {"type": "gem", **SMALL["gem"], "whiten": 16},
            },
            "tiers": [
                {"methods": ["netvlad", "gem", "gem_w", "gist_w"], "k": 2},
                {"methods": ["olo"], "k": 1},
            ],
        }
    )
    cache = FeatureCache(tmp_path / "cache")
    methods = build_methods(cfg)
    fitted = ["gem_w", "gist_w", "netvlad", "olo"]
    assert sorted(fit_methods(methods, paths, cache=cache)) == fitted
    read = extract_images(paths, methods, cache=cache, workers=1)
    assert read.cached == {**dict.fromkeys(fitted, 5), "gem": 0}  # gem fits nothing
    assert all(np.isfinite(read.ms[m]).all() for m in methods)
    fresh = extract_images(paths, methods, cache=None, workers=1)
    for i in range(len(paths)):
        for m in ("netvlad", "gist_w", "gem_w", "gem"):
            np.testing.assert_array_equal(read.features[m][i], fresh.features[m][i])
        got, want = read.features["olo"][i], fresh.features["olo"][i]
        np.testing.assert_array_equal(got.regions, want.regions)
        np.testing.assert_array_equal(got.words, want.words)
    # a fit on a subset (max_images) stores the features of the images it saw, no others
    cache2 = FeatureCache(tmp_path / "cache2")
    again = build_methods(cfg)
    fit_methods(again, paths, cache=cache2, max_images=3)
    assert extract_images(paths, again, cache=cache2, workers=1).cached["netvlad"] == 3


def test_a_cached_cnn_feature_is_not_computed_again_beside_a_missing_one(tmp_path: Path) -> None:
    """Of two batched methods, an image with one cached runs only the other: the cached
    feature is what comes back (a planted value proves it was read, not recomputed), and the
    other equals a fresh extraction."""
    paths = _image_files(tmp_path, 3, seed=5)
    cfg = parse_config(
        {
            "methods": {"gem": SMALL["gem"], "hybridnet": SMALL["hybridnet"]},
            "tiers": [{"methods": ["gem", "hybridnet"], "k": 1}],
        }
    )
    methods = build_methods(cfg)
    fresh = extract_images(paths, methods, cache=None, workers=1)
    cache = FeatureCache(tmp_path / "cache")
    planted = np.full_like(fresh.features["gem"][1], 0.5)
    cache.put(methods["gem"], file_digest(paths[1]), planted, 1.0)
    read = extract_images(paths, methods, cache=cache, workers=1)
    assert read.cached == {"gem": 1, "hybridnet": 0}
    np.testing.assert_array_equal(read.features["gem"][1], planted)
    for i in (0, 2):
        np.testing.assert_array_equal(read.features["gem"][i], fresh.features["gem"][i])
    for i in range(3):
        np.testing.assert_array_equal(read.features["hybridnet"][i], fresh.features["hybridnet"][i])


def test_extract_query_parallel_tasks_equal_serial(fitted: dict[str, object]) -> None:
    """The service splits a query into tasks (a forward-pass group each, a task per other
    method) on a thread pool; features and the per-method times' keys match a serial run."""
    from concurrent.futures import ThreadPoolExecutor

    from hmpf.features import extract_query

    methods = {**fitted, "gist": create_method("gist"), "hog": create_method("hog")}
    img = _images(1, seed=21)[0]
    ms_serial: dict[str, float] = {}
    ms_parallel: dict[str, float] = {}
    serial = extract_query(methods, img, ms_serial)  # type: ignore[arg-type]
    with ThreadPoolExecutor(3) as pool:
        parallel = extract_query(methods, img, ms_parallel, pool)  # type: ignore[arg-type]
    assert list(parallel) == list(methods) == list(serial)
    assert set(ms_parallel) == set(ms_serial) == set(methods)
    for name in methods:
        a, b = serial[name], parallel[name]
        if name == "olo":
            a, b = a.regions, b.regions
        np.testing.assert_array_equal(a, b)


def test_missing_torch_is_an_install_hint_not_a_traceback() -> None:
    """Without torch (blocked in a fresh interpreter, as in a venv without the cnn extra), a CNN
    method's extraction raises MissingDependencyError naming the extra to install."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np\n"
        "from hmpf.errors import MissingDependencyError\n"
        "from hmpf.methods import create_method\n"
        "from hmpf.methods.cnn import forward_group\n"
        "m = create_method('gem', {})\n"
        "try:\n"
        "    list(forward_group([m], [np.zeros((64, 64, 3), np.uint8)]))\n"
        "except MissingDependencyError as e:\n"
        "    print('HINT', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HINT" in out.stdout and "hmpf[cnn]" in out.stdout
