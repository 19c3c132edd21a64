"""Binary local descriptors for ``kaze`` / ``inliers`` (``descriptor: beblid | teblid | orb``):
config validation, cache keys, the Hamming fast path against brute force, real Gardens Point
frames, and an index round trip."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from hmpf.config import build_methods, parse_config
from hmpf.datasets import list_images
from hmpf.errors import ConfigError
from hmpf.features import extract_images
from hmpf.imageio import load_image
from hmpf.index import IndexReader
from hmpf.methods import create_method
from hmpf.methods.inliers import match_points
from hmpf.methods.kaze import KazeFeatures, hamming_nearest_two, match_distance
from indexer.build import BuildOptions, build
from tests.conftest import synthetic_image

BINARY = ("beblid", "teblid", "orb")


def test_the_contrib_wheel_offers_beblid_and_teblid() -> None:
    assert int(cv2.__version__.split(".")[0]) == 4  # pinned below 5 (KAZE, HOGDescriptor)
    assert cv2.xfeatures2d.BEBLID.create(6.25) is not None
    assert cv2.xfeatures2d.TEBLID.create(6.25) is not None


def test_descriptor_options_are_validated() -> None:
    with pytest.raises(ConfigError, match="descriptor"):
        create_method("kaze", {"descriptor": "sift"})
    with pytest.raises(ConfigError, match="descriptor_bits 512 is not offered by descriptor 'orb'"):
        create_method("kaze", {"descriptor": "orb", "descriptor_bits": 512})
    with pytest.raises(ConfigError, match="binary only"):
        create_method("kaze", {"descriptor_bits": 256})
    with pytest.raises(ConfigError, match="descriptor_bits"):
        create_method("inliers", {"descriptor": "teblid", "descriptor_bits": 128})
    with pytest.raises(ConfigError, match="scale_factor applies to beblid / teblid"):
        create_method("kaze", {"descriptor": "orb", "scale_factor": 1.0})
    with pytest.raises(ConfigError, match="scale_factor"):
        create_method("kaze", {"descriptor": "beblid", "scale_factor": 0})
    bits = {
        d: create_method("kaze", {"descriptor": d}).config.bits  # type: ignore[attr-defined]
        for d in BINARY
    }
    assert bits == {"beblid": 512, "teblid": 256, "orb": 256}


def test_cache_keys_differ_per_descriptor_and_kaze_keeps_its_key() -> None:
    kaze = create_method("kaze")
    # The options left unset do not enter the dump: the key is the one computed before they
    # existed (name, version 3, the seven extraction/matching options and n_best, pad_value).
    assert kaze.cache_key() == "kaze-44f0c10fadc3e05b"
    assert create_method("kaze", {"descriptor": "kaze"}).cache_key() == kaze.cache_key()
    assert "descriptor" not in kaze.config.model_dump()
    keys = {kaze.cache_key()}
    for d in BINARY:
        keys.add(create_method("kaze", {"descriptor": d}).cache_key())
    keys.add(create_method("kaze", {"descriptor": "teblid", "descriptor_bits": 512}).cache_key())
    keys.add(create_method("kaze", {"descriptor": "teblid", "scale_factor": 5.0}).cache_key())
    assert len(keys) == 6
    # inliers shares the cached features of the kaze with the same extraction settings.
    inl = create_method("inliers", {"descriptor": "teblid"})
    assert inl.descriptor_key() == create_method("kaze", {"descriptor": "teblid"}).cache_key()
    dumped = inl.config.model_dump()
    assert dumped["descriptor"] == "teblid" and "descriptor_bits" not in dumped
    assert create_method("inliers", dumped).cache_key() == inl.cache_key()  # round trip


def _brute_hamming(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    bits_q, bits_r = np.unpackbits(q, axis=1), np.unpackbits(r, axis=1)
    return (bits_q[:, None, :] != bits_r[None, :, :]).sum(axis=2)


def test_hamming_fast_path_equals_brute_force() -> None:
    rng = np.random.default_rng(3)
    q = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    r = rng.integers(0, 256, (70, 32), dtype=np.uint8)
    r[5] = q[0]  # an exact match
    r[9] = q[1]
    r[9, 0] ^= 1  # one bit off
    h = _brute_hamming(q, r)
    ssd1, ssd2, nearest = hamming_nearest_two(q, r)
    two = np.sort(h, axis=1)[:, :2]
    np.testing.assert_array_equal(ssd1, 4.0 * two[:, 0] / 256)
    np.testing.assert_array_equal(ssd2, 4.0 * two[:, 1] / 256)
    np.testing.assert_array_equal(h[np.arange(40), nearest], two[:, 0])
    assert nearest[0] == 5 and ssd1[0] == 0 and nearest[1] == 9 and ssd1[1] == 4 / 256
    # One reference row: no second neighbour; none: no neighbour at all.
    s1, s2, n = hamming_nearest_two(q, r[:1])
    np.testing.assert_array_equal(s1, 4.0 * h[:, 0] / 256)
    assert np.isinf(s2).all() and (n == 0).all()
    s1, s2, _ = hamming_nearest_two(q, r[:0])
    assert np.isinf(s1).all() and np.isinf(s2).all()
    with pytest.raises(ValueError, match="uint8 of one width"):
        hamming_nearest_two(q, rng.integers(0, 256, (3, 64), dtype=np.uint8))

    # Kaze.scores on a packed set (ragged, one empty reference) equals the brute force.
    m = create_method("kaze", {"descriptor": "teblid", "match_threshold": 30, "max_ratio": 0.9})
    kp = np.zeros((1, 5), np.float32)
    sizes = [70, 0, 1, 12, 33]
    feats, start = [], 0
    for n in sizes:
        rows = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        if n == 12:
            rows[:6] = q[:6] ^ np.uint8(16)  # six near matches (one bit a byte off)
        feats.append(KazeFeatures(np.repeat(kp, n, axis=0), rows))
        start += n
    feats[0] = KazeFeatures(np.repeat(kp, 70, axis=0), r)
    query = KazeFeatures(np.repeat(kp, 40, axis=0), q)
    got = m.scores(query, m.stack(feats))
    want = []
    for f in feats:
        if len(f) == 0:
            want.append(20.0)
            continue
        hh = np.sort(_brute_hamming(q, f.descriptors), axis=1) * (4.0 / 256)
        s2 = hh[:, 1] if hh.shape[1] > 1 else np.full(40, np.inf)
        want.append(float(match_distance(hh[:, 0], s2, match_threshold=30, max_ratio=0.9)))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert got[3] == 20 - 6 * (1 - 0.5) and got[1] == 20.0  # six matches at SSD 4 * 32 / 256
    np.testing.assert_array_equal(m.scores(query, m.stack(feats), np.array([3, 0])), got[[3, 0]])


@pytest.mark.parametrize("descriptor", BINARY)
def test_features_are_packed_bits_on_kaze_keypoints(descriptor: str) -> None:
    img = synthetic_image(5, (240, 320))
    m = create_method("kaze", {"descriptor": descriptor, "max_keypoints": 200})
    f = m.extract(img)
    width = m.config.bits // 8  # type: ignore[attr-defined]
    assert f.descriptors.dtype == np.uint8 and f.descriptors.shape == (len(f), width)
    assert 50 <= len(f) <= 200
    kaze = create_method("kaze", {"max_keypoints": 200}).extract(img)
    # The same keypoints as KAZE's (ORB drops those too close to the border).
    kept = {tuple(k) for k in kaze.keypoints[:, :2].tolist()}
    assert {tuple(k) for k in f.keypoints[:, :2].tolist()} <= kept
    if descriptor != "orb":
        np.testing.assert_array_equal(f.keypoints, kaze.keypoints)
    empty = m.extract(np.full((240, 320, 3), 127, np.uint8))
    assert len(empty) == 0 and empty.descriptors.shape == (0, width)
    assert m.scores(empty, m.stack([f]))[0] == 20.0
    assert m.scores(f, m.stack([empty, f]))[0] == 20.0


@pytest.mark.dataset
@pytest.mark.parametrize("descriptor", ["teblid", "beblid"])
def test_gardens_point_pair_matches_more_than_a_mismatched_pair(
    gardens_point: Path, descriptor: str
) -> None:
    # day_left -> day_right (lateral shift): the same frame has a lower KAZE distance, more
    # matches and more verified inliers than a frame 60 further on the route (when written,
    # ratio 0.8: TEBLID 43 / 25 matches against 1 / 2, BEBLID 36 / 9 against 0 / 1).
    p = {"descriptor": descriptor, "max_keypoints": 300, "max_ratio": 0.8}
    k, v = create_method("kaze", p), create_method("inliers", p)
    left, right = list_images(gardens_point / "day_left"), list_images(gardens_point / "day_right")
    for f in (20, 150):
        q = k.extract(load_image(left[f]))
        refs = k.stack([k.extract(load_image(right[i])) for i in (f, (f + 60) % 200)])
        d = k.scores(q, refs)
        assert d[0] < d[1], (f, d)
        same, other = (match_points(q, refs[i], max_ratio=0.8) for i in (0, 1))
        assert len(same[0]) >= 8 > len(other[0]), (f, len(same[0]), len(other[0]))
        inl = v.scores(q, refs)
        assert inl[0] >= 8 > inl[1], (f, inl)


CONFIG = {
    "name": "teblid-test",
    "methods": {"kaze": {"descriptor": "teblid", "max_keypoints": 150}},
    "tiers": [{"methods": ["gist"], "k": 3}, {"methods": ["kaze"], "k": 1}],
}


def test_index_round_trip_with_a_binary_descriptor(tmp_path: Path) -> None:
    refs_dir = tmp_path / "refs"
    refs_dir.mkdir()
    for i in range(5):
        cv2.imwrite(str(refs_dir / f"r{i:02d}.png"), synthetic_image(60 + i, (240, 320)))
    config = parse_config(CONFIG)
    index = tmp_path / "index"
    summary = build(config, refs_dir, index, options=BuildOptions(workers=1, progress=False))
    methods = build_methods(config)
    refs = list_images(refs_dir)
    ref = extract_images(refs, methods, workers=1)
    m = methods["kaze"]
    with IndexReader(index, expected_config=config) as reader:
        stored = reader.local_features("kaze", np.arange(5))
        for got, want in zip(stored, ref.features["kaze"], strict=True):
            assert got.descriptors.dtype == np.uint8
            np.testing.assert_array_equal(got.descriptors, want.descriptors)
            np.testing.assert_array_equal(got.keypoints, want.keypoints)
        query = load_image(refs[3])
        q = reader.extract_query(query)
        db = m.stack(ref.features["kaze"])
        np.testing.assert_array_equal(m.scores(q["kaze"], m.stack(stored)), m.scores(q["kaze"], db))
        assert reader.hierarchy().run(reader.scorer(q), reader.n).match == 3
        # The service's evidence draws the Hamming matches (the same image: many pairs).
        from service.evidence import evidence_method, render_evidence

        assert evidence_method(reader) == "kaze"
        out = render_evidence(reader, query, 3, reader.thumbnail(3))  # type: ignore[arg-type]
        assert out.method == "kaze" and out.pairs >= 10
    # Stored: float16 keypoints (5 values) and 32 bytes of descriptor per keypoint.
    n_kp = sum(len(f) for f in ref.features["kaze"])
    assert n_kp * (5 * 2 + 32) <= summary.bytes_per_method["kaze"] <= n_kp * 42 + 4096
