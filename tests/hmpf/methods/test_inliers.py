"""Geometric verification (``inliers``): synthetic warps with a known answer, real Gardens
Point frames, determinism, edge cases, the descriptor cache it shares with KAZE, and an index
round trip through ``hmpf-index build``, ``hmpf-eval --index`` and the service."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hmpf.config import build_methods, parse_config
from hmpf.datasets import list_images
from hmpf.errors import ConfigError
from hmpf.features import extract_images
from hmpf.hierarchy import Hierarchy, feature_scorer
from hmpf.imageio import load_image
from hmpf.index import IndexReader
from hmpf.methods import create_method
from hmpf.methods.inliers import Inliers, match_points
from hmpf.methods.kaze import KazeFeatures, best_two_ssd, nearest_two
from indexer.build import BuildOptions, build
from tests.conftest import synthetic_image

SIZE = (240, 320)
#: A mild perspective warp (a few degrees of rotation, shift, scale, some keystone).
WARP = np.array([[1.04, 0.05, 9.0], [-0.03, 0.97, 6.0], [1e-4, -5e-5, 1.0]])


def _warped(img: np.ndarray, h: np.ndarray = WARP) -> np.ndarray:
    return cv2.warpPerspective(img, h, (img.shape[1], img.shape[0]), borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def scenes() -> dict[str, KazeFeatures]:
    m = create_method("inliers")
    a, b = synthetic_image(11, SIZE), synthetic_image(12, SIZE)
    return {
        "a": m.extract(a),
        "a_warped": m.extract(_warped(a)),
        "b": m.extract(b),
        "b_warped": m.extract(_warped(b)),
        "blank": m.extract(np.full((*SIZE, 3), 127, np.uint8)),
    }


@pytest.mark.parametrize("model", ["homography", "fundamental"])
def test_same_place_warped_has_many_inliers_another_place_few(scenes, model) -> None:
    m = create_method("inliers", {"model": model})
    refs = m.stack([scenes["a"], scenes["b"]])
    for query, right in (("a_warped", 0), ("b_warped", 1)):
        s = m.scores(scenes[query], refs)
        assert s.shape == (2,) and s.dtype == np.float64
        assert s[right] >= 40, (model, query, s)
        assert s[1 - right] <= s[right] / 4, (model, query, s)


def test_homography_inliers_agree_with_the_known_warp(scenes) -> None:
    # Matched points of the warped copy lie where the true warp puts them: the ground truth
    # says most matches are right, and the model keeps (nearly) only those.
    m = create_method("inliers")
    src, dst = match_points(scenes["a_warped"], scenes["a"])
    # KAZE keypoints are in the 300 x 300 frame; map them to pixels, apply the inverse warp.
    sx, sy = (SIZE[1] - 1) / 300.0, (SIZE[0] - 1) / 300.0
    to_px = np.array([sx, sy], np.float32)
    back = cv2.perspectiveTransform((src * to_px)[None].astype(np.float64), np.linalg.inv(WARP))
    err = np.linalg.norm(back[0] - dst * to_px, axis=1)
    right = int(np.sum(err < 3.0))
    got = m.scores(scenes["a_warped"], [scenes["a"]])[0]
    assert right >= 40
    assert 0.8 * right <= got <= len(src)


def test_scores_are_deterministic_and_independent_of_order(scenes) -> None:
    m = create_method("inliers", {"estimator": "ransac", "max_iters": 50})
    feats = [scenes[k] for k in ("a", "b", "a_warped", "b_warped")]
    refs = m.stack(feats)
    q = scenes["a_warped"]
    first = m.scores(q, refs)
    again = create_method("inliers", {"estimator": "ransac", "max_iters": 50}).scores(q, refs)
    np.testing.assert_array_equal(first, again)
    subset = np.array([3, 1, 0, 1])
    np.testing.assert_array_equal(m.scores(q, refs, subset), first[subset])
    np.testing.assert_array_equal(m.scores(q, feats), first)  # a list works like the set


def test_featureless_images_score_zero(scenes) -> None:
    m = create_method("inliers")
    blank = scenes["blank"]
    assert len(blank) == 0
    np.testing.assert_array_equal(m.scores(blank, [scenes["a"], scenes["b"]]), [0.0, 0.0])
    np.testing.assert_array_equal(m.scores(scenes["a"], [blank, scenes["a"]])[:1], [0.0])
    assert m.scores(scenes["a"], [scenes["a"]], np.array([], np.int64)).shape == (0,)
    # Fewer matches than min_matches: 0, not a model fitted on too few points.
    strict = create_method("inliers", {"min_matches": 10_000})
    np.testing.assert_array_equal(strict.scores(scenes["a"], [scenes["a"]]), [0.0])


def test_matches_are_unique_per_reference_keypoint(scenes) -> None:
    q, r = scenes["a_warped"], scenes["a"]
    src, dst = match_points(q, r)
    assert len(np.unique(dst, axis=0)) == len(dst)
    many_src, _ = match_points(q, r, unique=False)
    assert len(many_src) >= len(src)


def test_config_is_validated_and_shares_kaze_cache_entries() -> None:
    with pytest.raises(ConfigError, match="model"):
        create_method("inliers", {"model": "affine"})
    with pytest.raises(ConfigError, match="n_best"):
        create_method("inliers", {"n_best": 5})  # a KAZE distance option, not this method's
    a = create_method("inliers")
    b = create_method("inliers", {"model": "fundamental"})
    assert a.cache_key() != b.cache_key()
    # Same extraction settings: the features KAZE cached are reused (and the other way).
    assert a.descriptor_key() == b.descriptor_key() == create_method("kaze").cache_key()
    small = create_method("inliers", {"max_keypoints": 100})
    assert small.descriptor_key() == create_method("kaze", {"max_keypoints": 100}).cache_key()
    assert small.descriptor_key() != a.descriptor_key()
    assert isinstance(a, Inliers) and a.higher_is_better and a.kind == "local"


@pytest.mark.dataset
def test_gardens_point_same_place_beats_far_places(gardens_point: Path) -> None:
    # Lateral shift (day_left -> day_right): among 20 references 10 frames apart, the same
    # frame has the most inliers for most queries (all 4 when this was written: 10, 7, 45 and
    # 28 inliers against at most 5 elsewhere).
    m = create_method("inliers", {"max_keypoints": 300})
    left, right = list_images(gardens_point / "day_left"), list_images(gardens_point / "day_right")
    refs = m.stack([m.extract(load_image(right[i])) for i in range(0, 200, 10)])
    best, same = [], []
    for f in (10, 60, 110, 160):
        s = m.scores(m.extract(load_image(left[f])), refs)
        best.append(int(np.argmax(s)) == f // 10)
        same.append(s[f // 10])
    assert sum(best) >= 3, (best, same)
    assert max(same) >= 20


CONFIG = {
    "name": "inliers-test",
    "methods": {"inliers": {"max_keypoints": 120}},
    "tiers": [{"methods": ["hog", "gist"], "k": 3}, {"methods": ["gist", "inliers"], "k": 1}],
}


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path, dict[str, int]]:
    base = tmp_path_factory.mktemp("inliers")
    refs, queries = base / "refs", base / "queries"
    refs.mkdir()
    queries.mkdir()
    for i in range(6):
        img = synthetic_image(40 + i, SIZE)
        cv2.imwrite(str(refs / f"r{i:02d}.png"), img[:, :, ::-1])
        cv2.imwrite(str(queries / f"r{i:02d}.png"), _warped(img)[:, :, ::-1])
    index = base / "index"
    summary = build(
        parse_config(CONFIG), refs, index, options=BuildOptions(workers=1, progress=False)
    )
    return refs, queries, index, summary.bytes_per_method


def test_index_round_trip_scores_as_in_memory(built) -> None:
    refs_dir, queries_dir, index, sizes = built
    config = parse_config(CONFIG)
    methods = build_methods(config)
    refs, queries = list_images(refs_dir), list_images(queries_dir)
    ref = extract_images(refs, methods, workers=1)
    qry = extract_images(queries, methods, workers=1)
    db = {m: methods[m].stack(ref.features[m]) for m in methods}
    hier = Hierarchy(config, methods)
    with IndexReader(index, expected_config=config) as reader:
        stored = reader.local_features("inliers", np.array([4, 1]))
        want_all = [ref.features["inliers"][4], ref.features["inliers"][1]]
        for got, want in zip(stored, want_all, strict=True):
            np.testing.assert_array_equal(got.keypoints, want.keypoints)
            np.testing.assert_array_equal(got.descriptors, want.descriptors)
        ihier = reader.hierarchy()
        for qi, path in enumerate(queries):
            q = {m: qry.features[m][qi] for m in methods}
            a = hier.run(feature_scorer(methods, q, db), len(refs))
            b = ihier.run(reader.scorer(reader.extract_query(load_image(path))), reader.n)
            np.testing.assert_array_equal(a.combined, b.combined)
            np.testing.assert_array_equal(a.tiers[1].raw["inliers"], b.tiers[1].raw["inliers"])
            assert a.match == b.match == qi  # each warped copy finds its original
            assert np.nanmax(a.tiers[1].raw["inliers"]) >= 20
    # What the build stored for the method: float16 keypoints (5) and descriptors (64) per
    # keypoint, plus the offsets.
    n_kp = sum(len(f) for f in ref.features["inliers"])
    assert n_kp * (5 + 64) * 2 <= sizes["inliers"] <= n_kp * (5 + 64) * 2 + 8 * 7 + 4096


def test_hmpf_eval_and_service_on_an_inliers_index(built, tmp_path, capsys) -> None:
    from fastapi.testclient import TestClient

    from hmpf.cli.eval import main as eval_main
    from service.app import create_app
    from service.auth import add_key
    from service.settings import load_settings

    refs_dir, queries_dir, index, _ = built
    out = tmp_path / "r.json"
    args = ["--index", str(index), "--query", str(queries_dir), "--no-cache", "--quiet"]
    assert eval_main([*args, "--workers", "1", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["hierarchy"]["matches"] == [f"r{i:02d}.png" for i in range(6)]
    # In memory (no index): the same answers, and the method's own curve over the database.
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(json.dumps(CONFIG))  # JSON is YAML
    mem = tmp_path / "m.json"
    args = ["--config", str(cfg), "--reference", str(refs_dir), "--query", str(queries_dir)]
    assert eval_main([*args, "--no-cache", "--quiet", "--workers", "1", "--json", str(mem)]) == 0
    rep = json.loads(mem.read_text())
    assert rep["hierarchy"]["matches"] == list(range(6))  # reference indices in memory
    assert rep["methods"]["inliers"]["recall_at"]["1"] == 1.0
    capsys.readouterr()

    keys = tmp_path / "keys.yaml"
    key = add_key(keys, "car-1", "vehicle")
    settings = load_settings(None, index=index, keys_file=keys, workers=1, queue=2)
    path = list_images(queries_dir)[2]
    with TestClient(create_app(settings)) as client:
        r = client.post(
            "/v1/localize",
            files={"image": (path.name, path.read_bytes(), "image/png")},
            headers={"X-API-Key": str(key)},
        )
    assert r.status_code == 200, r.text
    assert r.json()["match"]["name"] == "r02.png"


def test_nearest_two_equals_brute_force() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=(40, 64)).astype(np.float32)
    r = rng.normal(size=(70, 64)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    ssd1, ssd2, nearest = nearest_two(q, r)
    brute = ((q[:, None, :].astype(np.float64) - r[None, :, :]) ** 2).sum(-1)
    np.testing.assert_array_equal(nearest, brute.argmin(axis=1))
    two = np.sort(brute, axis=1)[:, :2]
    np.testing.assert_allclose(ssd1, two[:, 0], atol=1e-9)
    np.testing.assert_allclose(ssd2, two[:, 1], atol=1e-9)
    np.testing.assert_allclose(best_two_ssd(q, r)[0], ssd1, atol=1e-6)
    one = nearest_two(q, r[:1])
    assert np.isinf(one[1]).all() and (one[2] == 0).all()
    none = nearest_two(q, r[:0])
    assert np.isinf(none[0]).all() and np.isinf(none[1]).all()


def test_service_evidence_draws_inliers_matches(built) -> None:
    from service.evidence import evidence_method, render_evidence

    _, queries_dir, index, _ = built
    with IndexReader(index) as reader:
        assert evidence_method(reader) == "inliers"
        query = load_image(list_images(queries_dir)[1])
        out = render_evidence(reader, query, 1, reader.thumbnail(1))  # type: ignore[arg-type]
    assert out.method == "inliers" and out.pairs > 0
