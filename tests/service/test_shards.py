"""Region shards without Ray (:mod:`hmpf.shards`, :mod:`indexer.shard`, :mod:`hmpf.sharded`):
a real index of Gardens Point day_left (62 places with positions; GeM, a CNN, and Gist in
tier 1, HOG, SAD and KAZE deciding; a confidence model in its config) split by
``hmpf-index shard`` into 3 shards of 26 to 30 places (no shard, nor the map, a multiple of
a BLAS kernel's block) with an overlap; every night_right frame
of the same stretch answered by the sharded map equals, bit for bit, the unsharded answer
(match, scores, candidates, tiers, p_correct, accepted, the confidence features, the
sequence filter's estimates); a GPS prior reaches only the shards covering it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from hmpf.confidence import FEATURES, ConfidenceModel, answer_features
from hmpf.config import parse_config
from hmpf.sequence import Evidence
from hmpf.sharded import ShardedReader
from hmpf.shards import ShardError, ShardMap, plan, position_order, read_shard_map
from indexer.build import build
from indexer.cli import main as index_main
from service.answer import localize_response, on_references
from service.engine import Loaded, Prior, run_query
from service.schemas import LocalizeParams
from service.shards import open_sharded
from tests.conftest import copy_gp, write_positions
from tests.service_helpers import BUILD_OPTIONS

#: Places of the map and queries (night_right frames aligned with them).
N = 62
#: A CNN and Gist narrow (scored at every shard), HOG, SAD and KAZE (local) decide (scored
#: where the candidates live).
CONFIG = {
    "name": "shards-test",
    "methods": {"kaze": {"max_keypoints": 40}},
    "tiers": [{"methods": ["gem", "gist"], "k": 6}, {"methods": ["hog", "sad", "kaze"], "k": 1}],
    "sequence": {"lock_mass": 0.9},
}
SINGLE = (*FEATURES, "ref_z")


def _model() -> dict[str, Any]:
    """A fixed confidence model over the single-frame features (its numbers are not fitted:
    what matters is that p_correct reads every feature, the whole-map ones included)."""
    k = len(SINGLE)
    coef = (0.9, 0.7, 0.5, -0.6, 0.4, 0.8, -0.3, 0.6)
    model = ConfidenceModel(SINGLE, (1.0,) * k, (1.0,) * k, coef[:k], -1.0, 1.0)
    return {"threshold": 2.0, "model": model.to_dict(), "model_threshold": 0.5}


@pytest.fixture(scope="module")
def maps(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("shards")
    refs = copy_gp(gardens_point, "day_left", base / "refs", N)
    csv = write_positions(refs, base / "meta.csv")
    config = dict(CONFIG, acceptance=_model())
    index = base / "index"
    build(parse_config(config), refs, index, metadata=csv, options=BUILD_OPTIONS,
          with_map_prior=True)  # fmt: skip
    out = base / "shards"
    assert index_main(["shard", "--index", str(index), "--shards", "3", "--overlap", "5",
                       "--out", str(out)]) == 0  # fmt: skip
    return {"index": index, "shards": out}


@pytest.fixture(scope="module")
def night(gardens_point: Path) -> list[np.ndarray]:
    paths = sorted((gardens_point / "night_right").iterdir())[:N]
    return [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in paths]


@pytest.fixture(scope="module")
def loaded(maps: dict[str, Path]) -> Any:
    whole = Loaded.open(maps["index"], None)
    sharded = open_sharded(ShardedReader.open_local(maps["shards"]), None)
    yield whole, sharded
    whole.reader.close()
    sharded.reader.close()


# -- the plan -------------------------------------------------------------------------------------
def test_plan_owns_every_place_once_and_overlaps_borders() -> None:
    order = np.array([5, 3, 9, 0, 1, 2, 8, 7, 6, 4])
    plans = plan(order, 3, 2)
    owned = np.concatenate([p.owned for p in plans])
    assert sorted(owned.tolist()) == list(range(10))
    # stretches along the order, each widened by 2 places on either side
    assert [p.owned.tolist() for p in plans] == [[3, 5, 9], [0, 1, 2, 8], [4, 6, 7]]
    assert plans[0].covered.tolist() == [0, 1, 3, 5, 9]
    assert plans[1].covered.tolist() == [0, 1, 2, 3, 6, 7, 8, 9]
    assert plans[2].covered.tolist() == [2, 4, 6, 7, 8]
    m = ShardMap.from_plans(10, plans)
    # a subset inside one shard's overlap goes to that shard only; a spread one to owners
    assert list(m.route(np.array([1, 9]))) == [0]
    assert m.route(np.array([1, 9]))[0][1].tolist() == [1, 4]  # local ids in shard 0
    spread = m.route(np.array([5, 4]))
    assert sorted(spread) == [0, 2]


def test_position_order_cuts_compact_regions() -> None:
    """Places on a 4 x 4 grid (about 110 m apart both ways) in 4 shards by position: each
    shard owns one quadrant; places without a position come last."""
    cells = np.array([(i, j) for i in range(4) for j in range(4)], dtype=np.float64)
    lat = -27.0 + cells[:, 0] * 1e-3
    lon = 153.0 + cells[:, 1] * 1e-3 / np.cos(np.radians(lat.mean()))
    order = position_order(np.append(lat, np.nan), np.append(lon, 153.0))
    assert order[-1] == 16 and sorted(order.tolist()) == list(range(17))
    quadrants = []
    for p in plan(order[:16], 4, 0):
        owned = cells[p.owned].astype(int)
        quadrants.append((tuple(np.unique(owned[:, 0] // 2)), tuple(np.unique(owned[:, 1] // 2))))
    assert sorted(quadrants) == [((0,), (0,)), ((0,), (1,)), ((1,), (0,)), ((1,), (1,))]


@pytest.mark.parametrize(("shards", "overlap"), [(0, 0), (11, 0), (2, -1)])
def test_plan_refuses_bad_numbers(shards: int, overlap: int) -> None:
    with pytest.raises(ShardError):
        plan(np.arange(10), shards, overlap)


def test_split_writes_real_versions(maps: dict[str, Path]) -> None:
    shard_map, info = read_shard_map(maps["shards"])
    assert shard_map.shards == 3 and shard_map.n == N
    for s in range(3):
        cur = (maps["shards"] / shard_map.names[s] / "CURRENT").read_text().strip()
        assert cur == info["written"][s]
    counts = [len(c) for c in shard_map.covered]
    assert sum(len(shard_map.owned(s)[1]) for s in range(3)) == N
    assert sum(counts) == N + 2 * 2 * 5  # two borders, 5 places each side
    assert counts == [26, 30, 26]  # no size a multiple of a BLAS block (4), nor N


def test_split_cli_refuses_bad_input(maps: dict[str, Path], tmp_path: Path, capsys: Any) -> None:
    args = ["shard", "--index", str(maps["index"]), "--shards", "0", "--out", str(tmp_path / "x")]
    assert index_main(args) == 2
    assert "at least 1" in capsys.readouterr().err


# -- equality ------------------------------------------------------------------------------------
def _answer(loaded: Loaded, image: np.ndarray, params: LocalizeParams) -> tuple[dict, Any, Any]:
    timing: dict[str, Any] = {}
    result, allowed = run_query(loaded, image, params_prior(params), timing)
    answer = localize_response(loaded, result, allowed, params, timing).model_dump()
    answer.pop("timing_ms")
    answer.pop("index_version")
    for tier in answer["tiers"]:
        tier.pop("time_ms")  # wall time, the only number that may differ
    return answer, result, allowed


# float32 descriptor scores summed in another order (shards vs the whole map; BLAS kernels
# differ between machines): equal to float32 rounding, not always to the last bit (scores
# are normalised, of order 1: an absolute bound for those near 0)
RTOL = ATOL = 1e-6


def approx(a: Any, b: Any) -> bool:
    """``a == b``, floats (and float arrays) within :data:`RTOL` / :data:`ATOL`, recursively."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(approx(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(approx(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype.kind != "f" and b.dtype.kind != "f":
            return bool(np.array_equal(a, b))
        return bool(np.allclose(a, b, rtol=RTOL, atol=ATOL, equal_nan=True))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (a != a and b != b) or abs(a - b) <= ATOL + RTOL * max(abs(a), abs(b))
    return bool(a == b)


def params_prior(params: LocalizeParams) -> Prior | None:
    if params.lat is None:
        return None
    assert params.lon is not None and params.radius_m is not None
    return Prior(params.lat, params.lon, params.radius_m)


def test_sharded_answers_equal_unsharded_on_every_query(
    loaded: tuple[Loaded, Loaded], night: list[np.ndarray]
) -> None:
    whole, sharded = loaded
    # the split keeps the version's map prior: answers' features carry the same one
    assert whole.profile is not None and sharded.profile is not None
    assert whole.profile.map_prior is not None
    assert sharded.profile.map_prior == whole.profile.map_prior
    params = LocalizeParams(top_k=10)
    routes = whole.sequence.routes
    backend = sharded.reader.backend  # type: ignore[attr-defined]
    backend.calls.clear()
    accepted = 0
    state_w, state_s = whole.sequence.start(), sharded.sequence.start()
    for i, image in enumerate(night):
        a, ra, _ = _answer(whole, image, params)
        b, rb, _ = _answer(sharded, image, params)
        assert approx(a, b), f"frame {i}: {a} != {b}"
        assert a["match"]["p_correct"] is not None
        accepted += a["match"]["accepted"]
        # the evidence behind it: the same candidates, scores to float32 rounding
        assert np.array_equal(ra.final_candidates, rb.final_candidates)
        assert approx(ra.combined, rb.combined)
        for ta, tb in zip(ra.tiers, rb.tiers, strict=True):
            for m in ta.methods:
                assert approx(ta.scores[m], tb.scores[m]), (i, m)
                assert approx(ta.raw[m], tb.raw[m]), (i, m)
        fa = answer_features(ra, routes, profile=whole.profile)
        fb = answer_features(rb, sharded.sequence.routes, profile=sharded.profile)
        assert approx(fa, fb)
        # the sequence filter fed by either gives the same estimates
        ea = Evidence.from_result(ra, whole.reader.n)
        eb = Evidence.from_result(rb, sharded.reader.n)
        state_w, est_w = whole.sequence.update(state_w, ea)
        state_s, est_s = sharded.sequence.update(state_s, eb)
        assert est_w.ref == est_s.ref and approx(est_w.mass, est_s.mass)
    assert 0 < accepted < len(night)  # the model's decision is exercised both ways
    # tier 1 at every shard; the deciding tier's candidates at one shard, or split between
    # their owners (both happen)
    sizes = [len(c) for c in backend.calls]
    assert len(sizes) == 4 * len(night)  # tier 1 (both methods in one call), HOG, SAD, KAZE
    assert sizes.count(1) > 0 and sizes.count(2) + sizes.count(3) > len(night), sizes


def test_split_by_position_answers_equal(
    maps: dict[str, Path], loaded: tuple[Loaded, Loaded], night: list[np.ndarray], tmp_path: Path
) -> None:
    whole, _ = loaded
    out = tmp_path / "by-position"
    args = ["shard", "--index", str(maps["index"]), "--shards", "4", "--overlap", "2"]
    assert index_main([*args, "--by", "position", "--out", str(out)]) == 0
    assert read_shard_map(out)[1]["by"] == "position"
    sharded = open_sharded(ShardedReader.open_local(out), None)
    try:
        for i in range(0, N, 5):
            params = LocalizeParams(top_k=5)
            assert approx(
                _answer(whole, night[i], params)[0], _answer(sharded, night[i], params)[0]
            )
    finally:
        sharded.reader.close()
    with pytest.raises(SystemExit) as refused:
        index_main([*args, "--by", "nowhere", "--out", str(out)])
    assert refused.value.code == 2


def test_gps_prior_reaches_only_covering_shards(
    loaded: tuple[Loaded, Loaded], night: list[np.ndarray]
) -> None:
    whole, sharded = loaded
    reader = sharded.reader
    backend = reader.backend
    assert isinstance(reader, ShardedReader)
    # a prior around a place owned by the last shard, far from its first border
    shard_map = reader.map
    _, own = shard_map.owned(2)
    centre = int(own[len(own) // 2])
    lat, lon = float(whole.lat[centre]), float(whole.lon[centre])  # type: ignore[index]
    params = LocalizeParams(lat=lat, lon=lon, radius_m=40.0)
    for i in (centre - 2, centre, centre + 2):
        backend.calls.clear()
        a, ra, allowed_a = _answer(whole, night[i], params)
        b, rb, allowed_b = _answer(sharded, night[i], params)
        assert approx(a, b)
        assert np.array_equal(allowed_a, allowed_b) and len(allowed_a) < N
        assert backend.calls and all(c == [2] for c in backend.calls), backend.calls
        fa = answer_features(on_references(ra, allowed_a, N), whole.sequence.routes)
        fb = answer_features(on_references(rb, allowed_b, N), sharded.sequence.routes)
        assert fa == fb
    # without a prior, tier 1 reaches every shard
    backend.calls.clear()
    _answer(sharded, night[0], LocalizeParams())
    assert backend.calls[0] == [0, 1, 2]


def test_serve_shards_command_help_and_errors(maps: dict[str, Path], capsys: Any) -> None:
    """``hmpf-serve shards``: its help, and bad input refused (exit 2) before Ray starts."""
    from service.cli import main as serve_main

    with pytest.raises(SystemExit) as done:
        serve_main(["shards", "--help"])
    assert done.value.code == 0
    assert "--replicas-of NAME=N" in capsys.readouterr().out
    assert serve_main(["shards", "--shards", str(maps["index"])]) == 2
    assert "no shards.json" in capsys.readouterr().err
    assert serve_main(["shards", "--shards", str(maps["shards"]), "--replicas-of", "x=2"]) == 2
    assert "no shard 'x'" in capsys.readouterr().err
    assert serve_main(["shards", "--shards", str(maps["shards"]), "--replicas", "0"]) == 2


def test_euclidean_distance_of_a_row_does_not_depend_on_the_others(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """What exactness rests on: one query's distance to a reference is the same number in a
    call over the whole map, over a shard or subset of it (any length, any offset), and on
    one or two threads (a large call is split over the compute threads)."""
    from hmpf import runtime
    from hmpf.methods.base import euclidean

    rng = np.random.default_rng(3)
    # unit descriptors (as GeM's), a query near one of them: distances of order 1, where a
    # last-bit difference in a dot product shows
    refs = rng.standard_normal((4099, 1031)).astype(np.float32)  # > the parallel threshold
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)
    q = refs[100:101] + 0.05 * rng.standard_normal((1, 1031)).astype(np.float32)
    q /= np.linalg.norm(q)
    monkeypatch.setattr(runtime, "_threads", 2)
    whole = euclidean(q, refs)[0]
    monkeypatch.setattr(runtime, "_threads", 1)
    assert np.array_equal(euclidean(q, refs)[0], whole)
    for lo, hi in ((0, 1), (1, 4), (5, 26), (7, 2058), (4093, 4099)):
        assert np.array_equal(euclidean(q, refs[lo:hi])[0], whole[lo:hi]), (lo, hi)
    pick = rng.choice(len(refs), 37, replace=False)
    assert np.array_equal(euclidean(q, refs[pick])[0], whole[pick])


# -- a filter that weighs motion ---------------------------------------------------------------
@pytest.fixture(scope="module")
def moving(maps: dict[str, Path]) -> Any:
    """The same references under a config whose filter weighs motion, whole and split."""
    base = maps["index"].parent
    config = dict(CONFIG, acceptance=_model(), sequence={"lock_mass": 0.9, "stop_factor": 0.1})
    index = base / "moving"
    build(parse_config(config), base / "refs", index, metadata=base / "meta.csv",
          options=BUILD_OPTIONS)  # fmt: skip
    out = base / "moving-shards"
    assert index_main(["shard", "--index", str(index), "--shards", "2", "--out", str(out)]) == 0
    whole = Loaded.open(index, None)
    sharded = open_sharded(ShardedReader.open_local(out), None)
    yield whole, sharded
    whole.reader.close()
    sharded.reader.close()


def test_a_filter_that_weighs_motion_is_served_sharded_as_unsharded(
    moving: tuple[Loaded, Loaded], night: list[np.ndarray]
) -> None:
    whole, sharded = moving
    assert whole.motion is not None and sharded.motion is not None
    (mid_w, sk_w), (mid_s, sk_s) = whole.motion, sharded.motion
    assert mid_w == mid_s and sk_w.step == sk_s.step
    assert np.array_equal(sk_w.projection, sk_s.projection)
    states = [whole.sequence.start(), sharded.sequence.start()]
    stopped = 0
    for i, image in enumerate(night):
        estimates = []
        for k, loaded in enumerate((whole, sharded)):
            feats: dict[str, Any] = {}
            result, allowed = run_query(loaded, image, None, {}, None, feats)
            assert loaded.motion is not None
            mid, sketch = loaded.motion
            ev = Evidence.from_result(result, loaded.reader.n, sketch=sketch(feats[mid]))
            states[k], est = loaded.sequence.update(states[k], ev)
            estimates.append(est)
        a, b = estimates
        assert a.ref == b.ref and approx(a.mass, b.mass), f"frame {i}: {a} != {b}"
        stopped += a.speed == 0
    assert stopped < len(night)  # the cue let the estimate move on


def test_a_split_without_the_sketch_is_refused_for_a_filter_that_weighs_motion(
    moving: tuple[Loaded, Loaded], tmp_path: Path
) -> None:
    src = moving[1].reader.folder  # type: ignore[attr-defined]
    old = tmp_path / "old-split"
    shutil.copytree(src, old)
    doc = json.loads((old / "shards.json").read_text())
    doc.pop("motion_sketch")
    (old / "shards.json").write_text(json.dumps(doc))
    with pytest.raises(ShardError, match="no motion sketch"):
        open_sharded(ShardedReader.open_local(old), None)
    # a split that says the version had no sketch either serves without one, as it would
    doc["motion_sketch"] = None
    (old / "shards.json").write_text(json.dumps(doc))
    none = open_sharded(ShardedReader.open_local(old), None)
    try:
        assert none.motion is None
    finally:
        none.reader.close()
