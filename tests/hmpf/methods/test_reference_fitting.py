"""Fitting on the references: PCA-whitening and database-side augmentation (``dba``).

The whitening fit against a brute-force covariance eigendecomposition, DBA against a
per-row loop, the keys, config validation, fit + extraction against the bench's derived
route, and the fitted state and DBA through a real index build / reload / add (HDF5, FAISS).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.datasets import list_images
from hmpf.errors import ConfigError
from hmpf.features import fit_methods
from hmpf.imageio import load_image
from hmpf.index import IndexReader
from hmpf.methods import create_method
from hmpf.methods.base import apply_whitening, euclidean, fit_whitening, route_dba
from indexer.build import BuildOptions, add, build
from tests.conftest import synthetic_image, write_synthetic_images

OPTS = BuildOptions(workers=1, progress=False)


def _brute_whitening(x: np.ndarray, dims: int, power: float, shrink: float) -> np.ndarray:
    """Whitened, L2-normalised rows by the textbook route: np.cov, np.linalg.eig."""
    c = np.cov(x.T)  # (D, D), n - 1 normalisation
    ev, vec = np.linalg.eig(c)
    ev, vec = ev.real, vec.real
    order = np.argsort(ev)[::-1]
    p = min(dims, len(x) - 1, x.shape[1])
    lam, axes = ev[order][:p], vec[:, order][:, :p]
    lam = np.maximum(lam, 1e-9 * lam.max()) + shrink * np.maximum(lam, 1e-9 * lam.max()).mean()
    y = (x - x.mean(0)) @ axes / lam**power
    return y / np.linalg.norm(y, axis=1, keepdims=True)


@pytest.mark.parametrize("n,d", [(60, 12), (15, 40)])  # covariance path, SVD path
@pytest.mark.parametrize("power,shrink", [(0.5, 0.0), (0.25, 1.0)])
def test_whitening_matches_brute_force(n, d, power, shrink):
    rng = np.random.default_rng(n + d)
    x = rng.normal(size=(n, d)) * np.linspace(5, 0.1, d) + rng.normal(size=d)
    dims = 8
    mean, proj = fit_whitening(x, dims, power=power, shrink=shrink)
    assert proj.shape == (d, min(dims, n - 1, d))
    # Axis signs differ between the two routes; distances do not.
    got = apply_whitening(x, mean, proj)
    ref = _brute_whitening(x, dims, power, shrink)
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    assert np.allclose(euclidean(got, got), euclidean(ref, ref), atol=2e-4)


def test_full_whitening_gives_identity_covariance():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 10)) * np.arange(1, 11)
    mean, proj = fit_whitening(x, 6, power=0.5, shrink=0.0)
    y = (x - mean) @ proj
    assert np.allclose(np.cov(y.T), np.eye(6), atol=1e-4)


def test_dims_capped_by_references_and_bad_input():
    x = np.random.default_rng(1).normal(size=(5, 30))
    assert fit_whitening(x, 4096)[1].shape == (30, 4)  # n - 1 directions carry variance
    with pytest.raises(ValueError, match="at least 2"):
        fit_whitening(x[:1], 4)


def test_route_dba_matches_brute_force():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(9, 5)).astype(np.float32)
    for k in (1, 3, 12):
        want = np.zeros_like(x)
        for i in range(len(x)):
            for j in range(-k, k + 1):
                if 0 <= i + j < len(x):
                    want[i] += (1 - abs(j) / (k + 1)) * x[i + j]
        plain = (
            want
            / np.array(
                [
                    sum(1 - abs(j) / (k + 1) for j in range(-k, k + 1) if 0 <= i + j < len(x))
                    for i in range(len(x))
                ]
            )[:, None]
        )
        want /= np.linalg.norm(want, axis=1, keepdims=True)
        assert np.allclose(route_dba(x, k), want, atol=1e-6)
        assert np.allclose(route_dba(x, k, normalise=False), plain, atol=1e-5)
    assert route_dba(x, 0) is x


def test_sad_dba_stays_uint8_and_rounds_the_mean():
    sad = create_method("sad", {"dba": 1})
    x = np.array([[0, 100], [10, 200], [20, 255]], dtype=np.uint8)
    got = sad.augment_references(x)
    assert got.dtype == np.uint8
    # weights 1 (self), 0.5 (neighbours): row 0 = (0 + 0.5*10)/1.5, row 1 = (5 + 10 + 10)/2
    assert got.tolist() == [[3, 133], [10, 189], [17, 237]]


def _old_key(m) -> str:
    """The cache key as computed before the reference-fitting options existed."""
    cfg = {
        k: v
        for k, v in m.config.model_dump().items()
        if k not in ("whiten", "whiten_power", "whiten_shrink", "dba")
    }
    payload = json.dumps(
        {"name": m.name, "version": m.version, "config": cfg, "state": ""}, sort_keys=True
    )
    return f"{m.name}-{hashlib.sha256(payload.encode()).hexdigest()[:16]}"


def test_keys_change_with_the_options_only():
    for name in ("hog", "gist", "sad"):
        plain = create_method(name)
        assert plain.cache_key() == plain.descriptor_key() == _old_key(plain)
    hog = create_method("hog")
    white = create_method("hog", {"whiten": 64})
    power = create_method("hog", {"whiten": 64, "whiten_power": 0.25})
    dba = create_method("hog", {"dba": 2})
    keys = {m.cache_key() for m in (hog, white, power, dba)}
    assert len(keys) == 4
    # DBA changes the reference set, not an image's own descriptor: the cache is shared.
    assert dba.descriptor_key() == hog.descriptor_key() != dba.cache_key()
    assert white.descriptor_key() != hog.descriptor_key()
    # The fitted whitening enters the key.
    rng = np.random.default_rng(3)
    white.fit_references(rng.normal(size=(20, hog.dim)))
    before = white.cache_key()
    white.fit_references(rng.normal(size=(20, hog.dim)))
    assert white.cache_key() != before


@pytest.mark.parametrize(
    "name,params,match",
    [
        ("hog", {"whiten": 0}, "whiten"),
        ("hog", {"whiten": -3}, "whiten"),
        ("gist", {"whiten": 16, "whiten_power": 1.5}, "whiten_power"),
        ("gist", {"whiten": 16, "whiten_shrink": -1}, "whiten_shrink"),
        ("hog", {"whiten_power": 0.25}, "need whiten"),
        ("sad", {"dba": -1}, "dba"),
        ("gem", {"dba": 51}, "dba"),
        ("sad", {"faithful": True, "dba": 1}, "faithful"),
        ("netvlad", {"whiten": 64}, "whiten"),  # NetVLAD whitens with pca_dim
    ],
)
def test_bad_values_are_config_errors(name, params, match):
    with pytest.raises(ConfigError, match=match):
        create_method(name, params)


def test_unfitted_whitening_is_a_clear_error():
    with pytest.raises(RuntimeError, match="not fitted"):
        create_method("gist", {"whiten": 8}).extract(synthetic_image(0))


@pytest.mark.dataset
def test_fit_and_extraction_equal_the_bench_route(gardens_point):
    """hmpf's fit (fit_methods) + extraction equals fit_references on the references' own
    descriptors + finish, which bench/reference_fitting.py computes from cached features."""
    paths = list_images(gardens_point / "day_right")[:12]
    for name, params in (
        ("hog", {"whiten": 8, "whiten_power": 0.25, "whiten_shrink": 1.0}),
        ("sad", {"whiten": 5}),
    ):
        real = create_method(name, params)
        assert fit_methods({"m": real}, paths) == ["m"]
        plain, derived = create_method(name), create_method(name, params)
        raw = [plain.extract(load_image(p)) for p in paths]
        derived.fit_references(np.stack(raw))
        for p, r in zip(paths[:3], raw, strict=False):
            assert np.allclose(real.extract(load_image(p)), derived.finish(r), atol=1e-5)
        assert real.cache_key() == derived.cache_key()


def test_whitening_and_dba_through_an_index(tmp_path):
    cfg = parse_config(
        {
            "methods": {
                "hog": {"whiten": 6, "whiten_power": 0.25, "whiten_shrink": 0.1, "dba": 1},
                "gist": {"dba": 2},
            },
            "tiers": [{"methods": ["hog", "gist"], "k": 1}],
        }
    )
    a = write_synthetic_images(tmp_path / "a", 8)
    build(cfg, a, tmp_path / "index", options=OPTS)
    images = [synthetic_image(i) for i in range(8)]
    with IndexReader(tmp_path / "index") as r:
        hog = r.methods["hog"]
        assert hog.dim == 6 and set(hog.state_arrays()) == {"whiten_mean", "whiten_proj"}
        assert r.manifest["methods"]["hog"]["state_sha256"]
        own = np.stack([hog.extract(im) for im in images])  # queries: whitened, no DBA
        assert np.allclose(r.columns("hog"), own, atol=1e-5)  # stored: own descriptors
        searched = r.global_matrix("hog")  # searched: the route's DBA over them
        assert np.allclose(searched, route_dba(own, 1), atol=1e-5)
        gist_own = np.stack([r.methods["gist"].extract(im) for im in images])
        assert np.allclose(r.global_matrix("gist"), route_dba(gist_own, 2), atol=1e-5)
        # FAISS (exact, built from the searched matrix) agrees with brute force.
        ids, raw = r.search("hog", own[3], 3)
        brute = euclidean(own[3][None], searched)[0]
        assert ids[0] == int(brute.argmin())
        assert np.allclose(raw, np.sort(brute)[:3], atol=1e-4)
        state = hog.state_arrays()
    # A reload keeps the fitted state; adding references recomputes the DBA over the route.
    add(
        tmp_path / "index",
        write_synthetic_images(tmp_path / "b", 2, seed=8, prefix="z"),
        options=OPTS,
    )
    with IndexReader(tmp_path / "index") as r:
        hog = r.methods["hog"]
        for k, v in state.items():
            assert np.array_equal(hog.state_arrays()[k], v)
        own = np.stack([hog.extract(synthetic_image(i)) for i in range(10)])
        assert np.allclose(r.global_matrix("hog"), route_dba(own, 1), atol=1e-5)


def test_gem_whitening_fits_on_the_pooled_descriptors():
    """GeM (a CNN method, fitted through its forward-pass group) whitens after pooling and
    keeps float16 precision; the fit equals fit_references on plain GeM's descriptors."""
    pytest.importorskip("torch")
    images = [synthetic_image(i) for i in range(5)]
    params = {"whiten": 3, "whiten_power": 0.25, "whiten_shrink": 0.1}
    real, derived, plain = (create_method("gem", p) for p in (params, params, {}))
    from hmpf.methods.base import fit_many

    fit_many({"gem": real}, images)
    derived.fit_references(np.stack([plain.extract(im) for im in images]))
    got = real.extract(images[1])
    assert got.shape == (3,) and np.array_equal(got, got.astype(np.float16).astype(np.float32))
    assert np.allclose(got, derived.finish(plain.extract(images[1])), atol=2e-3)
    assert real.cache_key() == derived.cache_key()
