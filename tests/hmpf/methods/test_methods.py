"""Tests of the weight-free methods (Gist, KAZE, HOG, SAD), imops and the method registry.

Every reference below is written independently from the specification (docs/spec, §1, §2.2,
§2.3, §2.6, §2.7), not by calling the implementation's helpers, so that a wrong implementation
fails.
Tests that read the Gardens Point images are marked ``dataset`` and skip when it is absent.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmpf.datasets import dataset_root
from hmpf.errors import ConfigError, UnknownMethodError
from hmpf.imageio import load_image
from hmpf.imops import imresize, rgb2gray
from hmpf.methods import available_methods, create_method
from hmpf.methods.gist import prefilt
from hmpf.methods.kaze import KazeFeatures
from hmpf.methods.sad import patch_normalise

GARDENS = dataset_root() / "gardens_point"


def _image(folder: str, index: int) -> np.ndarray:
    path = GARDENS / folder / f"Image{index:03d}.jpg"
    if not path.is_file():
        pytest.skip(f"dataset image not available: {path}")
    return load_image(path)


# =============================================================================================
# Gist (spec §2.2) against a slow spatial-domain reference
# =============================================================================================


def _matlab_round(x: float) -> int:
    return int(math.floor(x + 0.5)) if x >= 0 else -int(math.floor(-x + 0.5))


def _circular_conv(x: np.ndarray, kernels: np.ndarray) -> np.ndarray:
    """Spatial circular convolution of the 2-D ``x`` with each of ``kernels`` (K, N, N).

    ``y[m, n] = sum_{a, b} k[a, b] x[(m - a) mod N, (n - b) mod N]`` as an explicit sum over
    shifts (np.roll), which equals ``ifft2(fft2(x) * fft2(k))``.
    """
    n0, n1 = x.shape
    assert kernels.shape[1:] == (n0, n1)
    out = np.zeros((kernels.shape[0], n0, n1), dtype=np.complex128)
    for a in range(n0):
        xa = np.roll(x, a, axis=0)
        for b in range(n1):
            out += kernels[:, a, b, None, None] * np.roll(xa, b, axis=1)[None]
    return out


def _ref_centered_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``[fx, fy] = meshgrid(-n/2 : n/2-1)`` for even n."""
    assert n % 2 == 0
    f = np.arange(-(n // 2), n // 2, dtype=np.float64)
    return np.meshgrid(f, f)


def _ref_prefilt(img: np.ndarray, fc: float) -> np.ndarray:
    """LMgist prefilt (§2.2 step 4), filtering by spatial circular convolution."""
    w = 5
    s1 = fc / math.sqrt(math.log(2))
    x = np.log(img.astype(np.float64) + 1.0)
    x = np.pad(x, w, mode="symmetric")
    sn, sm = x.shape
    n = max(sn, sm)
    if n % 2:
        n += 1
    x = np.pad(x, ((0, n - sn), (0, n - sm)), mode="symmetric")
    fx, fy = _ref_centered_grid(n)
    gf = np.fft.fftshift(np.exp(-(fx**2 + fy**2) / s1**2))
    kernel = np.fft.ifft2(gf)[None]  # spatial kernel of the transfer function
    out = x - np.real(_circular_conv(x, kernel)[0])
    localstd = np.sqrt(np.abs(_circular_conv(out**2, kernel)[0]))
    out = out / (0.2 + localstd)
    return out[w : sn - w, w : sm - w]


def _ref_gabor_bank(orientations: list[int], n: int) -> list[np.ndarray]:
    """createGabor (§2.2 step 5), one explicit loop iteration per filter."""
    fx, fy = _ref_centered_grid(n)
    fr = np.fft.fftshift(np.sqrt(fx**2 + fy**2))
    t = np.fft.fftshift(np.angle(fx + 1j * fy))
    bank = []
    for i, n_or in enumerate(orientations):  # i = 0: highest frequency
        for j in range(n_or):
            p1 = 0.35
            p2 = 0.3 / 1.85**i
            p3 = 16.0 * n_or**2 / 32.0**2
            p4 = math.pi / n_or * j
            tr = t + p4
            tr = np.where(tr < -math.pi, tr + 2 * math.pi, tr)
            tr = np.where(tr > math.pi, tr - 2 * math.pi, tr)
            bank.append(np.exp(-10 * p1 * (fr / n / p2 - 1) ** 2 - 2 * p3 * math.pi * tr**2))
    return bank


def _ref_gist(
    grey: np.ndarray, image_size: int, orientations: list[int], blocks: int, fc: float, be: int
) -> np.ndarray:
    # imresizecrop: aspect-preserving MATLAB bilinear resize, then centre crop.
    h, w = grey.shape
    s = max(image_size / h, image_size / w)
    nr, nc = _matlab_round(h * s), _matlab_round(w * s)
    img = imresize(grey.astype(np.float64), (nr, nc), "bilinear")
    sr, sc = (nr - image_size) // 2, (nc - image_size) // 2
    img = img[sr : sr + image_size, sc : sc + image_size]
    # Stretch to 0..255.
    img = img - img.min()
    img = 255.0 * img / img.max()
    out = _ref_prefilt(img, fc)
    padded = np.pad(out, be, mode="symmetric")
    n = image_size + 2 * be
    bank = _ref_gabor_bank(orientations, n)
    kernels = np.stack([np.fft.ifft2(g) for g in bank])
    responses = np.abs(_circular_conv(padded, kernels))[
        :, be : be + image_size, be : be + image_size
    ]
    edges = [int(np.trunc(v)) for v in np.linspace(0, image_size, blocks + 1)]
    feat = []
    for resp in responses:  # filters in scale-major order
        for bc in range(blocks):  # column-major block order: block row varies fastest
            for br in range(blocks):
                total, count = 0.0, 0
                for r in range(edges[br], edges[br + 1]):
                    for c in range(edges[bc], edges[bc + 1]):
                        total += resp[r, c]
                        count += 1
                feat.append(total / count)
    return np.array(feat)


def test_gist_matches_spatial_reference_on_small_image() -> None:
    params = {
        "image_size": 32,
        "boundary_extension": 8,
        "orientations_per_scale": [4, 4],
        "number_blocks": 4,
    }
    gist = create_method("gist", params)
    rng = np.random.default_rng(11)
    # Non-square so that the aspect-preserving resize and the centre crop both matter
    # (40x52 -> 32x42 (rounded from 41.6) -> columns 5..36).
    grey = rng.integers(0, 256, size=(40, 52)).astype(np.uint8)
    got = gist.describe(grey)
    ref = _ref_gist(grey, 32, [4, 4], 4, 4.0, 8)
    assert got.dtype == np.float32
    assert got.shape == (8 * 16,) == ref.shape
    assert gist.dim == 128
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7)


@pytest.mark.dataset
def test_gist_default_is_512_float32_on_real_image() -> None:
    img = _image("day_left", 0)
    gist = create_method("gist")
    feat = gist.extract(img)
    assert feat.shape == (512,)
    assert feat.dtype == np.float32
    assert np.all(np.isfinite(feat))
    assert float(np.abs(feat).max()) > 0
    other = gist.extract(_image("day_left", 100))
    d = gist.scores(feat, gist.stack([feat, other]))
    assert d[0] == pytest.approx(0.0, abs=1e-3)
    assert d[1] > 0


@pytest.mark.parametrize("blocks", [4, 3])
def test_gist_pruned_bank_equals_full_bank(blocks: int) -> None:
    # GaborLines skips frequency lines where a filter is below gabor_floor; the result must
    # equal the unpruned computation (floor 0) to single precision, for the LMgist defaults
    # and for block edges that do not divide the image (128 / 3).
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:180, 0:240]
    grey = 100 + 60 * np.sin(x / 7.0) * np.cos(y / 11.0) + rng.normal(0, 20, (180, 240))
    grey = np.clip(grey, 0, 255).astype(np.uint8)
    pruned = create_method("gist", {"number_blocks": blocks})
    full = create_method("gist", {"number_blocks": blocks, "gabor_floor": 0.0})
    assert len(full.bank.line_index) == 32 * 192
    assert len(pruned.bank.line_index) < 0.5 * 32 * 192  # the pruning is real
    a, b = pruned.describe(grey), full.describe(grey)
    assert a.shape == b.shape == (32 * blocks * blocks,)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * float(np.abs(b).max()))


def test_prefilt_constant_image_is_finite() -> None:
    out = prefilt(np.full((32, 40), 100.0), 4.0)
    assert out.shape == (32, 40)
    assert np.all(np.isfinite(out))
    gist = create_method(
        "gist", {"image_size": 32, "boundary_extension": 8, "orientations_per_scale": [4, 4]}
    )
    assert np.all(np.isfinite(gist.describe(np.full((40, 40), 7, dtype=np.uint8))))


# =============================================================================================
# KAZE (spec §2.3): vectorised scores against a brute-force matchFeatures reference
# =============================================================================================


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def _feat(desc: np.ndarray) -> KazeFeatures:
    desc = np.asarray(desc, dtype=np.float32).reshape(-1, 64)
    return KazeFeatures(np.zeros((desc.shape[0], 5), np.float32), desc)


def _ref_kaze(query: np.ndarray, ref: np.ndarray) -> tuple[float, int]:
    """matchFeatures(q, ref, MatchThreshold 20, MaxRatio 0.7) + pad-with-1 sum of 20 best.

    Returns (distance, number of kept matches).
    """
    q = query.astype(np.float64)
    r = ref.astype(np.float64)
    matched: list[float] = []
    for row in q:
        if r.shape[0] == 0:
            break
        ssd = [float(np.sum((row - d) ** 2)) for d in r]
        ordered = sorted(ssd)
        ssd1 = ordered[0]
        if ssd1 > 4.0 * 20 / 100:  # MatchThreshold 20 % of the SSD range [0, 4]
            continue
        if r.shape[0] > 1:  # MaxRatio only when the reference has more than one feature
            ssd2 = ordered[1]
            if ssd2 == 0 or ssd1 / ssd2 > 0.7:
                continue
        matched.append(ssd1)
    n_matches = len(matched)
    padded = sorted(matched + [1.0] * max(0, 20 - n_matches))
    return float(sum(padded[:20])), n_matches


@pytest.fixture(scope="module")
def kaze_sets() -> list[KazeFeatures]:
    """Synthetic descriptor sets: counts 0, 1, 2, 5, 30, 300 plus a 30-row query."""
    rng = np.random.default_rng(2024)

    def rand(n: int) -> np.ndarray:
        return _unit(rng.normal(size=(n, 64)))

    def near(v: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
        v = np.atleast_2d(v)
        sig = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (v.shape[0],))
        return _unit(v + sig[:, None] * rng.normal(size=v.shape) / 8.0)

    q = rand(30)
    r0 = np.zeros((0, 64), np.float32)
    r1 = near(q[0], 0.3)
    r2 = np.vstack([near(q[1], 0.2), rand(1)])
    # q[5] twice: nearest and second nearest both at SSD 0 -> rejected.
    r5 = np.vstack([near(q[2], 0.1), near(q[3], 0.6), q[5], q[5], rand(1)])
    r30 = np.vstack([near(q[:10], np.linspace(0.05, 1.4, 10)), rand(20)])
    r300 = np.vstack([near(q, np.linspace(0.02, 0.85, 30)), rand(270)])
    r300 = r300[rng.permutation(300)]
    return [_feat(x) for x in (r0, r1, r2, r5, r30, r300, q)]


def test_kaze_scores_match_bruteforce(kaze_sets: list[KazeFeatures]) -> None:
    kaze = create_method("kaze")
    refs = kaze.stack(kaze_sets)
    n_matches = np.zeros((len(refs), len(refs)), dtype=int)
    for qi, query in enumerate(kaze_sets):
        got = kaze.scores(query, refs)
        assert got.dtype == np.float64 and got.shape == (len(refs),)
        expected = []
        for ri, ref in enumerate(kaze_sets):
            d, m = _ref_kaze(query.descriptors, ref.descriptors)
            expected.append(d)
            n_matches[qi, ri] = m
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5, err_msg=f"query {qi}")
        # The reference without keypoints gives exactly 20.
        assert got[0] == 20.0
    q = len(kaze_sets) - 1
    # The data exercise every branch: < 20 matches, >= 20 matches, and some matches at all.
    assert 0 < n_matches[q, 4] < 20
    assert n_matches[q, 5] >= 20
    assert n_matches[q, 1] >= 1 and n_matches[q, 2] >= 1 and n_matches[q, 3] >= 1
    # r5 holds q[5] twice (SSD1 = SSD2 = 0: rejected), so only the near-duplicates of q[2] and
    # q[3] can match.
    assert n_matches[q, 3] <= 2
    # The empty query gives 20 against every reference.
    np.testing.assert_array_equal(kaze.scores(kaze_sets[0], refs), np.full(len(refs), 20.0))


def test_kaze_edge_shapes(kaze_sets: list[KazeFeatures]) -> None:
    kaze = create_method("kaze")
    r0, r1, q = kaze_sets[0], kaze_sets[1], kaze_sets[-1]
    # All references empty (n_max == 0) and references of at most one descriptor (n_max == 1).
    np.testing.assert_array_equal(kaze.scores(q, [r0, r0]), [20.0, 20.0])
    got = kaze.scores(q, [r0, r1, r1])
    expected = [_ref_kaze(q.descriptors, r.descriptors)[0] for r in (r0, r1, r1)]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    assert got[1] < 20.0  # one match, no ratio test with a single reference descriptor
    assert kaze.scores(q, [r0, r1], subset=np.array([], dtype=np.int64)).shape == (0,)


def test_kaze_subset_and_chunking(kaze_sets: list[KazeFeatures]) -> None:
    kaze = create_method("kaze")
    refs = kaze.stack(kaze_sets)
    query = kaze_sets[5]  # 300 descriptors
    full = kaze.scores(query, refs)
    subset = np.array([5, 0, 3, 3, 6, 1])
    # Same values up to float32 rounding (the packed block's shape changes the matmul order).
    np.testing.assert_allclose(
        kaze.scores(query, refs, subset=subset), full[subset], rtol=0, atol=1e-6
    )
    # 100 references with a 300x300 worst case span more than one packed chunk.
    many = [kaze_sets[i % len(kaze_sets)] for i in range(100)]
    expected = [
        _ref_kaze(query.descriptors, kaze_sets[i % len(kaze_sets)].descriptors)[0]
        for i in range(len(kaze_sets))
    ]
    got = kaze.scores(query, many)
    np.testing.assert_allclose(
        got, [expected[i % len(kaze_sets)] for i in range(100)], rtol=0, atol=1e-5
    )


def test_kaze_set_is_ragged_and_equivalent_to_a_list(kaze_sets: list[KazeFeatures]) -> None:
    kaze = create_method("kaze")
    packed = kaze.stack(kaze_sets)
    counts = [len(f) for f in kaze_sets]
    assert len(packed) == len(kaze_sets)
    np.testing.assert_array_equal(packed.counts, counts)
    np.testing.assert_array_equal(packed.offsets, np.concatenate([[0], np.cumsum(counts)]))
    for i, f in enumerate(kaze_sets):
        np.testing.assert_array_equal(packed[i].descriptors, f.descriptors)
    np.testing.assert_array_equal(
        kaze.scores(kaze_sets[4], packed), kaze.scores(kaze_sets[4], list(kaze_sets))
    )
    assert len(kaze.stack([])) == 0


@pytest.mark.dataset
def test_kaze_real_images() -> None:
    kaze = create_method("kaze")
    max_kp = kaze.config.max_keypoints
    assert max_kp == 500
    feats = [kaze.extract(_image("day_left", 10)), kaze.extract(_image("day_left", 150))]
    for f in feats:
        assert isinstance(f, KazeFeatures)
        n = len(f)
        assert 0 < n <= max_kp
        assert f.descriptors.dtype == np.float32
        assert f.descriptors.shape == (n, 64)
        assert f.keypoints.shape == (n, 5)
        # Unit norm, to float16 precision (descriptors are stored as float16 values).
        np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=2e-3)
        np.testing.assert_array_equal(f.descriptors.astype(np.float16), f.descriptors)
    d = kaze.scores(feats[0], kaze.stack(feats))
    assert d[0] < d[1]
    assert d[0] < 1.0  # every descriptor matches itself at SSD ~ 0
    # The vectorised path agrees with the brute-force reference on real descriptors.
    expected = [_ref_kaze(feats[0].descriptors, f.descriptors)[0] for f in feats]
    np.testing.assert_allclose(d, expected, rtol=0, atol=1e-4)


# =============================================================================================
# HOG (spec §2.6)
# =============================================================================================


@pytest.mark.dataset
def test_hog_real_images_and_euclidean() -> None:
    hog = create_method("hog")
    feats = [hog.extract(_image(f, 20)) for f in ("day_left", "day_right", "night_right")]
    for f in feats:
        assert f.shape == (2916,)
        assert f.dtype == np.float32
        assert np.all(np.isfinite(f))
        assert float(f.max()) > 0
    refs = hog.stack(feats)
    got = hog.pairwise(refs, refs)
    direct = np.array(
        [
            [np.linalg.norm(a.astype(np.float64) - b.astype(np.float64)) for b in feats]
            for a in feats
        ]
    )
    np.testing.assert_allclose(got, direct, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(hog.scores(feats[2], refs), direct[2], rtol=1e-6, atol=1e-6)


def test_hog_flat_image_is_finite() -> None:
    hog = create_method("hog")
    f = hog.extract(np.full((120, 160, 3), 128, dtype=np.uint8))
    assert f.shape == (2916,)
    assert f.dtype == np.float32
    assert np.all(np.isfinite(f))


# =============================================================================================
# SAD (spec §2.7)
# =============================================================================================


def test_sad_patch_normalise_hand_example() -> None:
    grey = np.array(
        [
            [0, 3, 7, 7],
            [10, 5, 7, 7],
            [1, 2, 9, 9],
            [3, 4, 9, 9],
        ],
        dtype=np.uint8,
    )
    out = patch_normalise(grey, 2)
    assert out.dtype == np.uint8
    expected = np.array(
        [
            # 255 * 3/10 = 76.5 -> 77 (MATLAB rounds halves away from zero); 127.5 -> 128
            [0, 77, 0, 0],
            [255, 128, 0, 0],
            # patch [1 2; 3 4]: 255 * k / 3 = 0, 85, 170, 255; flat patches -> 0
            [0, 85, 0, 0],
            [170, 255, 0, 0],
        ],
        dtype=np.uint8,
    )
    np.testing.assert_array_equal(out, expected)


@pytest.mark.dataset
def test_sad_real_image_template() -> None:
    sad = create_method("sad")
    t = sad.extract(_image("day_right", 30))
    assert t.shape == (2048,)
    assert t.dtype == np.uint8
    # Column-major flattening of 32 rows x 64 columns: every 8x8 patch spans 0..255.
    grid = t.reshape(32, 64, order="F")
    for r in range(0, 32, 8):
        for c in range(0, 64, 8):
            p = grid[r : r + 8, c : c + 8]
            assert (p.min(), p.max()) in {(0, 255), (0, 0)}


def test_sad_default_is_mean_absolute_difference() -> None:
    sad = create_method("sad")
    rng = np.random.default_rng(5)
    q = rng.integers(0, 256, size=(3, 2048)).astype(np.uint8)
    db = rng.integers(0, 256, size=(4, 2048)).astype(np.uint8)
    got = sad.pairwise(q, db)
    expected = np.array(
        [[np.mean(np.abs(d.astype(np.int64) - a.astype(np.int64))) for d in db] for a in q]
    )
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_sad_faithful_is_one_sided() -> None:
    q = np.zeros(2048, dtype=np.uint8)
    db = np.zeros(2048, dtype=np.uint8)
    q[:4] = [10, 200, 0, 255]
    db[:4] = [20, 100, 7, 0]
    # db - q saturating at 0 in uint8: 10 + 0 + 7 + 0 = 17.
    faithful = create_method("sad", {"faithful": True})
    default = create_method("sad")
    assert faithful.scores(q, faithful.stack([db]))[0] == pytest.approx(17 / 2048)
    assert default.scores(q, default.stack([db]))[0] == pytest.approx((10 + 100 + 7 + 255) / 2048)
    # Where db >= q everywhere both agree.
    db2 = np.maximum(db, q)
    assert faithful.scores(q, faithful.stack([db2]))[0] == pytest.approx(
        default.scores(q, default.stack([db2]))[0]
    )


# =============================================================================================
# imops (spec §1.4, §1.5)
# =============================================================================================


def test_imresize_same_size_is_identity() -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, size=(7, 9, 3)).astype(np.uint8)
    out = imresize(img, (7, 9), "lanczos3")
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, img)
    grey = img[..., 0]
    np.testing.assert_array_equal(imresize(grey, (7, 9), "bilinear"), grey)


def test_imresize_bilinear_halving_by_hand() -> None:
    # 1x8 -> 1x4, scale 0.5: u = x/0.5 + 0.5 (1 - 2) = 2x - 0.5 = 1.5, 3.5, 5.5, 7.5 (1-based).
    # Antialiased triangle h(d) = 0.5 tri(0.5 d), width 2 / 0.5 = 4: the taps at distances
    # 1.5, 0.5, 0.5, 1.5 weigh 1/8, 3/8, 3/8, 1/8 after normalisation. Tap 0 mirrors to
    # pixel 1 and tap 9 to pixel 8.
    x = np.array([[3.0, -1.0, 4.0, 1.5, 9.0, 2.0, 6.0, 5.0]])
    w = np.array([1 / 8, 3 / 8, 3 / 8, 1 / 8])
    x1 = x[0]
    expected = np.array(
        [
            w @ np.array([x1[0], x1[0], x1[1], x1[2]]),
            w @ x1[1:5],
            w @ x1[3:7],
            w @ np.array([x1[5], x1[6], x1[7], x1[7]]),
        ]
    )
    np.testing.assert_allclose(
        expected,
        [
            0.5 * 3 - 0.375 + 0.5,
            -0.125 + 1.5 + 0.5625 + 1.125,
            0.1875 + 3.375 + 0.75 + 0.75,
            0.25 + 2.25 + 2.5,
        ],
        rtol=1e-12,
    )
    got = imresize(x, (1, 4), "bilinear")
    assert got.dtype == np.float64 and got.shape == (1, 4)
    np.testing.assert_allclose(got[0], expected, rtol=1e-12, atol=1e-12)
    # The same along the other axis.
    np.testing.assert_allclose(imresize(x.T, (4, 1), "bilinear")[:, 0], expected, rtol=1e-12)


def test_rgb2gray_rounding() -> None:
    px = np.array(
        [
            [[255, 0, 0], [0, 255, 0], [0, 0, 255]],
            [[255, 255, 255], [10, 20, 30], [1, 1, 1]],
        ],
        dtype=np.uint8,
    )
    # 76.2195 -> 76, 149.685 -> 150, 29.07 -> 29, 254.9745 -> 255, 18.149 -> 18, 0.9999 -> 1
    expected = np.array([[76, 150, 29], [255, 18, 1]], dtype=np.uint8)
    out = rgb2gray(px)
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_allclose(rgb2gray(px.astype(np.float64))[1, 1], 18.149, rtol=1e-12)


def test_rgb2gray_exact_on_every_colour() -> None:
    # All 2^24 RGB triples against exact integer arithmetic (round half up of v / 10000).
    r, g, b = np.meshgrid(np.arange(256), np.arange(256), np.arange(256), indexing="ij")
    img = np.stack([r, g, b], axis=-1).reshape(4096, 4096, 3).astype(np.uint8)
    c = img.astype(np.int64)
    expected = (2989 * c[..., 0] + 5870 * c[..., 1] + 1140 * c[..., 2] + 5000) // 10000
    np.testing.assert_array_equal(rgb2gray(img), expected.astype(np.uint8))
    # Non-contiguous views and a single pixel keep their shape.
    assert rgb2gray(img[:7, ::3]).shape == (7, 1366)
    np.testing.assert_array_equal(rgb2gray(img[:1, :1]), expected[:1, :1])


# =============================================================================================
# Registry
# =============================================================================================


def test_unknown_method_lists_valid_names() -> None:
    with pytest.raises(UnknownMethodError) as info:
        create_method("nope")
    assert isinstance(info.value, ConfigError)
    msg = str(info.value)
    assert "nope" in msg
    names = available_methods()
    assert {"gist", "hog", "kaze", "sad"} <= set(names)
    for name in names:
        assert name in msg


def test_bad_config_key_is_named() -> None:
    with pytest.raises(ConfigError) as info:
        create_method("hog", {"cel_size": 3})
    assert "cel_size" in str(info.value)


@pytest.mark.parametrize(
    ("name", "change"),
    [
        ("gist", {"number_blocks": 2}),
        ("gist", {"fc_prefilt": 3.0}),
        ("hog", {"bins": 12}),
        ("hog", {"cell_size": 20}),
        ("kaze", {"max_keypoints": 100}),
        ("kaze", {"max_ratio": 0.8}),
        ("sad", {"faithful": True}),
    ],
)
def test_cache_key_tracks_config(name: str, change: dict[str, object]) -> None:
    base = create_method(name).cache_key()
    assert base == create_method(name).cache_key()
    assert base.startswith(f"{name}-")
    assert create_method(name, change).cache_key() != base


def test_euclidean_copies_a_matrix_to_float64_only_when_it_is_scored_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Rows a query gathers for itself are scored once: no float64 copy of them is made or
    kept (it cost more than the scoring); a matrix scored a second time keeps one. Both ways
    give the same numbers to the last bit, in blocks, on one thread or several."""
    from hmpf import runtime
    from hmpf.methods import base

    rng = np.random.default_rng(1)
    matrix = rng.standard_normal((700, 300)).astype(np.float16).astype(np.float32)
    q = rng.standard_normal((1, 300))
    first = base.euclidean(q, matrix)
    assert base._remembered(base._REF_CACHE, matrix) is None
    second = base.euclidean(q, matrix)
    assert base._remembered(base._REF_CACHE, matrix) is not None
    assert np.array_equal(first, second)
    monkeypatch.setattr(base, "_BLOCK", 300 * 7)  # blocks of 7 rows, the last one short
    monkeypatch.setattr(base, "_PARALLEL_DOTS", 300 * 50)  # split over the threads
    for threads in (1, 3):
        monkeypatch.setattr(runtime, "_threads", threads)
        assert np.array_equal(base.euclidean(q, matrix.copy()), first), threads
        assert np.array_equal(base.euclidean(q, matrix), first), threads  # the copy, split
    want = np.sqrt(((q - matrix.astype(np.float64)) ** 2).sum(1))
    np.testing.assert_allclose(first[0], want, rtol=1e-9)


def test_euclidean_cache_keeps_the_matrix_across_temporary_row_sets() -> None:
    """A large matrix scored every query keeps its float64 copy while the rows gathered
    per query (temporaries, each large enough to be remembered) come and go."""
    from hmpf.methods import base

    rng = np.random.default_rng(0)
    matrix = rng.standard_normal((300, 256)).astype(np.float32)
    q = rng.standard_normal((1, 256))
    first = base.euclidean(q, matrix)
    kept = base._as_f64_with_norms(matrix)[0]
    for _ in range(3 * base._REF_CACHE_SIZE):
        base.euclidean(q, rng.standard_normal((300, 256)).astype(np.float32))
    assert base._as_f64_with_norms(matrix)[0] is kept
    np.testing.assert_array_equal(base.euclidean(q, matrix), first)
    want = np.sqrt(((q.astype(np.float64) - matrix.astype(np.float64)) ** 2).sum(1))
    np.testing.assert_allclose(first[0], want, rtol=1e-9)


def test_imagenet_input_is_its_formula_to_the_last_bit() -> None:
    """The CNN input (channels first, each step in place over a channel plane) holds the
    numbers of the formula over interleaved channels, at every input size the presets use."""
    import cv2

    from hmpf.backbones.efficientnet import _MEAN, _STD, imagenet_input

    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (541, 963, 3), dtype=np.uint8)
    for size in ((416, 416), (320, 544), (224, 224), (128, 128), (7, 5)):
        got = imagenet_input(image, size)
        img = cv2.resize(image, (size[1], size[0]), interpolation=cv2.INTER_AREA)
        want = ((img.astype(np.float32) / 255.0 - _MEAN) / _STD).transpose(2, 0, 1)
        assert got.dtype == np.float32 and got.flags.c_contiguous
        assert got.shape == (3, *size)
        assert np.array_equal(got, want), size
