"""``p_correct`` and ``accepted_by`` in the service's answers (issue 17), on a real index
(Gardens Point day_right, 20 references with positions) and real night frames; no mocks.

A small :class:`~hmpf.confidence.ConfidenceModel` (and a sequence one) is fitted on the
answers of training frames, put in the config's ``acceptance`` and a version is *built* with
it (the config digest ignores ``acceptance``: the model is part of the built version's
stored config, not something patched in afterwards). Then:

* with a model: every answer carries ``p_correct`` in [0, 1], the very probability the model
  gives the answer's features, and ``accepted == (p_correct >= model_threshold)``,
  ``accepted_by == "p_correct"``; ``/v1/index`` lists the models;
* without one: ``p_correct`` null, ``accepted_by == "quality"`` (a sequence estimate:
  ``"lock"``, accepted when locked);
* under a GPS prior the features are computed on the right reference ids;
* sequence mode's estimate is decided by the sequence model;
* a model of another version, a corrupt one, or one that needs features the answer lacks:
  ``hmpf-serve`` refuses to start (exit 2, the reason on stderr), and a reload to such a
  version is a 409 that keeps the loaded version.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from hmpf.confidence import (
    FEATURES,
    PROFILE_FEATURES,
    SEQUENCE_FEATURES,
    ConfidenceModel,
    answer_features,
)
from hmpf.config import parse_config
from hmpf.index import layout
from hmpf.index.reader import IndexReader
from hmpf.sequence import Evidence, RouteMap, SequenceFilter
from indexer.build import build
from service.answer import on_references
from service.app import create_app
from service.auth import add_key
from service.cli import main as serve_main
from service.engine import restricted
from service.settings import load_settings
from tests.conftest import SERVICE_CONFIG
from tests.service_helpers import BUILD_OPTIONS, ROOT, evaluate_frames, nan_in_final_tier

#: Training frames (night_right, frame-aligned with day_right) and the test frames.
TRAIN = range(0, 20)
TEST = [3, 8, 12, 17]
#: The models read the absolute evidence too, so the service must build the profile.
SINGLE = (*FEATURES, "ref_z")
SEQUENCE = FEATURES + SEQUENCE_FEATURES + PROFILE_FEATURES
#: An answer within this many references of its frame is right.
TOLERANCE = 2


def _rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


@pytest.fixture(scope="module")
def night(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "night_right").iterdir())


@pytest.fixture(scope="module")
def models(service_index: Path, night: list[Path]) -> dict[str, Any]:
    """Single-frame and sequence models fitted on the training frames' real answers, with
    thresholds at their training medians (so that some answers pass and some do not)."""
    reader = IndexReader(service_index)
    try:
        hierarchy, routes = reader.hierarchy(), reader.route_map()
        profile = reader.reference_profile()
        filt_params = reader.config.sequence_params()
        filt = SequenceFilter(routes, filt_params)
        state = filt.start()
        single, seq, y1, y2 = [], [], [], []
        for i in TRAIN:
            result = hierarchy.run(reader.scorer(reader.extract_query(_rgb(night[i]))), reader.n)
            single.append(answer_features(result, routes, profile=profile))
            y1.append(abs(result.match - i) <= TOLERANCE)
            ev = Evidence.from_result(result, reader.n, proposals=filt_params.proposals)
            state, est = filt.update(state, ev)
            seq.append(answer_features(result, routes, estimate=est, profile=profile))
            y2.append(abs(est.ref - i) <= TOLERANCE)
    finally:
        reader.close()
    assert 0 < sum(y1) < len(y1), "the training answers must be both right and wrong"
    m1 = ConfidenceModel.fit(np.array([[f[n] for n in SINGLE] for f in single]), y1, SINGLE)
    m2 = ConfidenceModel.fit(np.array([[f[n] for n in SEQUENCE] for f in seq]), y2, SEQUENCE)
    t1 = float(np.median(m1.predict(np.array([[f[n] for n in SINGLE] for f in single]))))
    t2 = float(np.median(m2.predict(np.array([[f[n] for n in SEQUENCE] for f in seq]))))
    return {"model": m1, "threshold": t1, "sequence_model": m2, "sequence_threshold": t2}


def _acceptance(models: dict[str, Any]) -> dict[str, Any]:
    return {
        "threshold": 2.0,
        "model": models["model"].to_dict(),
        "model_threshold": models["threshold"],
        "sequence_model": models["sequence_model"].to_dict(),
        "sequence_threshold": models["sequence_threshold"],
    }


def _build_version(
    service_index: Path,
    root: Path,
    acceptance: dict[str, Any] | None,
    with_map_prior: bool | None = None,
) -> str:
    """Build a version of the service index's references at ``root`` (a new one when the
    root has versions already) with ``acceptance`` in its config (``with_map_prior``: as
    :func:`indexer.build.build`'s); returns its name."""
    config = dict(SERVICE_CONFIG, sequence={"lock_mass": 0.9})
    if acceptance is not None:
        config["acceptance"] = acceptance
    base = service_index.parent
    summary = build(
        parse_config(config), base / "refs", root, metadata=base / "meta.csv",
        options=BUILD_OPTIONS, with_map_prior=with_map_prior,
    )  # fmt: skip
    return summary.version


def _tamper(root: Path, version: str, change: Any) -> str:
    """A copy of ``version`` whose stored config's acceptance is changed by ``change`` (as
    an index made by another hmpf, or damaged, would hold it), made current."""
    return _copy_with(root, version, lambda m: change(m["config"]["resolved"]["acceptance"]))


def _copy_with(root: Path, version: str, change: Any) -> str:
    """A copy of ``version`` whose manifest is changed by ``change``, made current."""
    versions = layout.list_versions(root)
    new = f"v{int(versions[-1][1:]) + 1:04d}"
    shutil.copytree(root / version, root / new)
    path = root / new / layout.MANIFEST
    manifest = json.loads(path.read_text())
    manifest["version"] = new
    change(manifest)
    layout.write_manifest(path.parent, manifest)  # sealed: the change is what is checked
    layout.set_current(root, new)
    return new


@pytest.fixture(scope="module")
def model_index(
    service_index: Path, models: dict[str, Any], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    root = tmp_path_factory.mktemp("confidence") / "index"
    _build_version(service_index, root, _acceptance(models))
    return root


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("confidence-keys") / "keys.yaml"
    return {
        "file": str(path),
        "vehicle": add_key(path, "car", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


def _client(index: Path, keys: dict[str, str]) -> TestClient:
    settings = load_settings(None, index=index, keys_file=keys["file"], workers=1, queue=4)
    return TestClient(create_app(settings))


@pytest.fixture(scope="module")
def client(model_index: Path, keys: dict[str, str]) -> Iterator[TestClient]:
    with _client(model_index, keys) as c:
        yield c


def _post(c: TestClient, keys: dict[str, str], path: Path, **fields: Any) -> dict[str, Any]:
    r = c.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        data={k: str(v) for k, v in fields.items()},
        headers={"X-API-Key": keys["vehicle"]},
    )
    assert r.status_code == 200, r.text
    return dict(r.json())


def test_the_built_version_holds_the_models(model_index: Path, models: dict[str, Any]) -> None:
    reader = IndexReader(model_index)
    try:
        acc = reader.config.acceptance
        assert acc is not None and acc.model_threshold == models["threshold"]
        assert acc.confidence_model() == models["model"]
        assert acc.confidence_model(sequence=True) == models["sequence_model"]
    finally:
        reader.close()


def test_answers_carry_p_correct_and_the_model_decides(
    client: TestClient, keys: dict[str, str], night: list[Path], models: dict[str, Any],
    model_index: Path,
) -> None:  # fmt: skip
    reader = IndexReader(model_index)
    try:
        hierarchy, routes = reader.hierarchy(), reader.route_map()
        seen = set()
        for i in TEST:
            body = _post(client, keys, night[i])
            m = body["match"]
            assert m["accepted_by"] == "p_correct" and body["single"] == m
            assert 0.0 <= m["p_correct"] <= 1.0
            assert m["accepted"] == (m["p_correct"] >= models["threshold"])
            seen.add(m["accepted"])
            # The very probability the model gives this answer's features.
            result = hierarchy.run(reader.scorer(reader.extract_query(_rgb(night[i]))), reader.n)
            assert result.match == m["reference_id"]
            feats = answer_features(result, routes, profile=reader.reference_profile())
            want = models["model"].predict(feats)
            assert m["p_correct"] == pytest.approx(want, rel=1e-9, abs=1e-12)
    finally:
        reader.close()
    assert seen == {True, False}, "the test frames should fall on both sides of the threshold"
    info = client.get("/v1/index", headers={"X-API-Key": keys["vehicle"]}).json()
    assert info["acceptance"] == {
        "rule": "p_correct",
        "sequence_rule": "p_correct",
        "threshold": 2.0,
        "model": {
            "features": list(SINGLE),
            "threshold": models["threshold"],
            "stay_threshold": None,
            "stay_ref_z": None,
        },
        "sequence_model": {
            "features": list(SEQUENCE),
            "threshold": models["sequence_threshold"],
            "stay_threshold": None,
            "stay_ref_z": None,
        },
        "lock_mass": 0.9,  # the version's sequence settings (see _build_version)
        "unlock_mass": 0.9,  # the lock rule's stay bar, never above lock_mass
        # no model reads the map's prior
        "map_prior": None,
        "map_prior_stored": None,
        "map_prior_fallback": None,
    }
    doc = client.get("/openapi.json").json()["components"]["schemas"]["Match"]["properties"]
    for name in ("p_correct", "accepted_by"):
        assert "hmpf-calibrate" in doc["p_correct"]["description"] and doc[name]["description"]
    assert set(doc["accepted_by"]["enum"]) == {"p_correct", "quality", "lock"}


def test_without_a_model_p_correct_is_null_and_the_quality_rule_decides(
    service_index: Path, keys: dict[str, str], night: list[Path]
) -> None:
    with _client(service_index, keys) as c:
        body = _post(c, keys, night[TEST[0]])
        m = body["match"]
        assert m["p_correct"] is None and m["accepted_by"] == "quality"
        assert m["accepted"] == (m["score"] >= body["threshold"])
        info = c.get("/v1/index", headers={"X-API-Key": keys["vehicle"]}).json()
        assert info["acceptance"]["rule"] == "quality"
        assert info["acceptance"]["model"] is None and info["acceptance"]["sequence_model"] is None
        # sequence mode without a sequence model: the lock decides
        for i in range(5):
            body = _post(c, keys, night[i], vehicle_id="car-1", **(
                {"track": body["sequence"]["track"]} if i else {}
            ))  # fmt: skip
            est = body["sequence"]["match"]
            assert est["p_correct"] is None and est["accepted_by"] == "lock"
            assert est["accepted"] == body["sequence"]["locked"]


def test_gps_prior_answer_gets_p_correct_on_the_right_reference_ids(
    client: TestClient, keys: dict[str, str], night: list[Path], models: dict[str, Any],
    model_index: Path,
) -> None:  # fmt: skip
    from tests.conftest import BASE_LAT, BASE_LON, STEP_LAT

    i = 12
    lo = 6  # the prior allows references 6..17 (contiguous along the route)
    lat = BASE_LAT + (lo + 5.5) * STEP_LAT
    radius = 6.0 * STEP_LAT * 111_195.0
    body = _post(client, keys, night[i], lat=lat, lon=BASE_LON, radius_m=radius)
    m = body["match"]
    assert body["prior"]["applied"] and body["prior"]["references"] == 12
    reader = IndexReader(model_index)
    try:
        allowed = np.arange(lo, lo + 12)
        feats = reader.extract_query(_rgb(night[i]))
        sub = reader.hierarchy().run(restricted(reader.scorer(feats), allowed), len(allowed))
        assert allowed[sub.match] == m["reference_id"]
        full = on_references(sub, allowed, reader.n)
        profile = reader.reference_profile()
        on_ids = answer_features(full, reader.route_map(), profile=profile)
    finally:
        reader.close()
    # Independently: the sub-database's own route (positions 0..11 along the same route
    # stretch) gives the same evidence, route distances and absolute evidence included.
    own = answer_features(
        sub, RouteMap.from_metadata(len(allowed)), profile=profile.subset(allowed)
    )
    assert "ref_z" in own and np.isfinite(own["ref_z"])
    assert on_ids == pytest.approx(own)
    assert m["accepted_by"] == "p_correct"
    assert m["p_correct"] == pytest.approx(models["model"].predict(on_ids), rel=1e-9, abs=1e-12)
    assert m["accepted"] == (m["p_correct"] >= models["threshold"])
    # A prior that leaves a single reference still answers, with a probability.
    one = _post(client, keys, night[i], lat=BASE_LAT + i * STEP_LAT, lon=BASE_LON, radius_m=2.0)
    assert one["prior"]["references"] == 1 and one["match"]["reference_id"] == i
    assert one["match"]["p_correct"] is None or 0 <= one["match"]["p_correct"] <= 1


def test_sequence_mode_uses_the_sequence_model(
    client: TestClient, keys: dict[str, str], night: list[Path], models: dict[str, Any]
) -> None:
    track = None
    differs = False
    for i in range(0, 12):
        fields: dict[str, Any] = {"vehicle_id": "car-7", "timestamp": i / 2.0}
        if track is not None:
            fields["track"] = track
        body = _post(client, keys, night[i], **fields)
        track = body["sequence"]["track"]
        assert body["match_source"] == "sequence"
        est = body["match"]
        assert est == body["sequence"]["match"] and est["accepted_by"] == "p_correct"
        assert 0.0 <= est["p_correct"] <= 1.0
        assert est["accepted"] == (est["p_correct"] >= models["sequence_threshold"])
        single = body["single"]
        assert single["accepted_by"] == "p_correct"
        assert single["accepted"] == (single["p_correct"] >= models["threshold"])
        differs = differs or est["p_correct"] != pytest.approx(single["p_correct"])
    assert differs, "the estimate's probability comes from the sequence model"


# -- models that cannot be used --------------------------------------------------------------
def _another_version(acc: dict[str, Any]) -> None:
    acc["model"]["version"] = 3


def _corrupt(acc: dict[str, Any]) -> None:
    acc["sequence_model"]["coef"] = acc["sequence_model"]["coef"][:-1]


def _sequence_features_in_single_model(acc: dict[str, Any]) -> None:
    acc["model"] = acc["sequence_model"]


def _no_threshold(acc: dict[str, Any]) -> None:
    del acc["model_threshold"]


BAD = {
    "another_version": (_another_version, "version 3 is not supported"),
    "corrupt": (_corrupt, "'coef' must hold"),
    "sequence_features_in_single_model": (_sequence_features_in_single_model, "sequence_mass"),
    "no_threshold": (_no_threshold, "needs its threshold"),
}


def _never_serve(monkeypatch: pytest.MonkeyPatch) -> None:
    """A refusal that regresses fails the test instead of serving (and waiting) for ever."""

    def serving(*_: Any) -> int:
        raise AssertionError("hmpf-serve accepted the index and would have started serving")

    monkeypatch.setattr("service.cli._run_server", serving)


@pytest.mark.parametrize("case", list(BAD))
def test_serve_refuses_an_index_whose_model_cannot_be_used(
    case: str, model_index: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    _never_serve(monkeypatch)
    change, reason = BAD[case]
    root = tmp_path / "index"
    shutil.copytree(model_index, root)
    _tamper(root, layout.current_version(root) or "", change)
    monkeypatch.setenv("HMPF_AUTH", "false")
    assert serve_main(["--index", str(root), "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "hmpf-serve: error:" in err and reason in err and "Traceback" not in err


def test_serve_subprocess_exits_2_with_the_reason(model_index: Path, tmp_path: Path) -> None:
    root = tmp_path / "index"
    shutil.copytree(model_index, root)
    _tamper(root, layout.current_version(root) or "", _another_version)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_")}
    env.update(HMPF_AUTH="false", PYTHONPATH=str(ROOT))
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "--index", str(root), "--port", "1"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "confidence model version 3 is not supported" in done.stderr
    assert "Traceback" not in done.stderr


def test_reload_to_a_model_and_refusing_a_bad_one(
    service_index: Path, models: dict[str, Any], keys: dict[str, str], night: list[Path],
    tmp_path: Path,
) -> None:  # fmt: skip
    root = tmp_path / "index"
    shutil.copytree(service_index, root)
    admin = {"X-API-Key": keys["admin"]}
    with _client(root, keys) as c:
        assert _post(c, keys, night[TEST[1]])["match"]["accepted_by"] == "quality"
        good = _build_version(service_index, root, _acceptance(models))
        r = c.post("/v1/index/reload", headers=admin)
        assert r.status_code == 200 and r.json()["version"] == good, r.text
        m = _post(c, keys, night[TEST[1]])["match"]
        assert m["accepted_by"] == "p_correct" and 0 <= m["p_correct"] <= 1
        for change, reason in BAD.values():
            _tamper(root, good, change)
            r = c.post("/v1/index/reload", headers=admin)
            assert r.status_code == 409, r.text
            error = r.json()["error"]
            assert error["code"] == "index_unusable" and reason in error["message"]
            assert f"kept version {good}" in error["message"]
            body = _post(c, keys, night[TEST[1]])
            assert body["index_version"] == good and body["match"] == m


def test_a_match_without_a_finite_score_gets_no_probability(model_index: Path, night) -> None:
    """A method that scores NaN for a final candidate makes the Combined z NaN: with a model,
    ``p_correct`` is null (not a probability of made-up features) and the match is not
    accepted."""
    from service.answer import localize_response
    from service.engine import Loaded
    from service.schemas import LocalizeParams

    loaded = Loaded.open(model_index, threshold=None)
    try:
        real = loaded.reader.scorer(loaded.reader.extract_query(_rgb(night[TEST[0]])))
        result = loaded.hierarchy.run(nan_in_final_tier(real), loaded.reader.n)
        assert np.isnan(result.quality) and result.match >= 0
        answer = localize_response(loaded, result, None, LocalizeParams(), {"total": 1.0})
    finally:
        loaded.reader.close()
    assert answer.match is not None and answer.match.score is None
    assert answer.match.p_correct is None and answer.match.accepted is False
    assert answer.match.accepted_by == "p_correct"


def test_on_references_puts_a_prior_result_on_the_whole_map() -> None:
    """Positions 0 and 1 of a prior that allowed references 3 and 9: next to each other in
    the sub-database, six route steps apart on the map. The rival is a rival only on the
    map's ids, which is what the service's features must see."""
    from hmpf.hierarchy import HierarchyResult, TierResult

    allowed = np.array([3, 9, 10])
    s = {"a": np.array([1.0, 0.8, 0.0]), "b": np.array([1.0, 0.9, np.nan])}
    tier = TierResult(["a", "b"], None, s, np.array([0, 1]), 0.1)
    sub = HierarchyResult(0, 0.7, np.array([0, 1]), np.array([0.7, -0.7]), [tier])
    full = on_references(sub, allowed, 12)
    assert full.match == 3 and full.final_candidates.tolist() == [3, 9]
    t = full.tiers[0]
    assert t.candidates.tolist() == [3, 9] and t.inputs is not None
    assert t.inputs.tolist() == [3, 9, 10]
    assert np.isnan(t.scores["a"][[0, 1, 2, 4, 11]]).all()
    assert t.scores["a"][[3, 9, 10]].tolist() == [1.0, 0.8, 0.0]
    routes = RouteMap.from_metadata(12)
    on_map = answer_features(full, routes)
    assert on_map["margin"] == pytest.approx(0.7 - -0.7)  # reference 9 is a real rival
    naive = answer_features(sub, RouteMap.from_metadata(3))  # positions read as ids
    assert naive["margin"] == pytest.approx(0.7)  # "next door": no rival
    assert on_references(sub, None, 12) is sub


def test_batch_answers_carry_p_correct(
    client: TestClient, keys: dict[str, str], night: list[Path], models: dict[str, Any]
) -> None:
    files = [("images", (night[i].name, night[i].read_bytes(), "image/jpeg")) for i in TEST[:2]]
    for data in ({}, {"vehicle_id": "car-9"}):
        r = client.post(
            "/v1/localize/batch", files=files, data=data, headers={"X-API-Key": keys["vehicle"]}
        )
        assert r.status_code == 200, r.text
        for item in r.json()["results"]:
            m, single = item["result"]["match"], item["result"]["single"]
            assert m["accepted_by"] == "p_correct" and 0 <= m["p_correct"] <= 1
            assert item["result"]["match_source"] == ("sequence" if data else "single")
            thr = models["sequence_threshold" if data else "threshold"]
            assert m["accepted"] == (m["p_correct"] >= thr)
            assert single["accepted"] == (single["p_correct"] >= models["threshold"])


def test_hmpf_eval_on_the_index_gives_the_services_p_correct(
    client: TestClient, keys: dict[str, str], night: list[Path], model_index: Path
) -> None:
    """hmpf-eval --index runs the service's policy (hmpf.acceptance) with the same absolute
    evidence (the reader's reference profile): the same p_correct and the same accepted per
    frame, single frame and in sequence mode (the frames driven in order, one vehicle)."""
    order = list(range(0, 12))
    frames = [night[i] for i in order]
    rep = evaluate_frames(model_index, frames, order, TOLERANCE)
    single, seq = rep["acceptance"]["single"], rep["acceptance"]["sequence"]
    assert single["rule"] == "p_correct" and seq["rule"] == "p_correct"
    answers = [_post(client, keys, f)["match"] for f in frames]
    assert single["p_correct"] == pytest.approx([a["p_correct"] for a in answers], abs=1e-12)
    assert single["accepted_answers"] == [a["accepted"] for a in answers]
    track, served, off = None, [], []
    for i, f in enumerate(frames):
        fields: dict[str, Any] = {"vehicle_id": "car-parity", "timestamp": float(i)}
        if track is not None:
            fields["track"] = track
        body = _post(client, keys, f, **fields)
        track = body["sequence"]["track"]
        served.append(body["sequence"]["match"])
        off.append(body["sequence"]["off_map"])
    # The token carries the belief as float16 logs: probabilities agree to ~1e-3.
    assert seq["p_correct"] == pytest.approx([m["p_correct"] for m in served], abs=5e-3)
    assert seq["accepted_answers"] == [m["accepted"] for m in served]
    assert seq["off_map"] == off


# -- a model that reads the map's prior ---------------------------------------------------------
def _with_offset(model: dict[str, Any]) -> dict[str, Any]:
    """``model`` with ``map_prior`` added as an offset (coefficient 1, unscaled), as the
    acceptance benches fit it."""
    return {
        **model,
        "features": [*model["features"], "map_prior"],
        "mean": [*model["mean"], 0.0],
        "scale": [*model["scale"], 1.0],
        "coef": [*model["coef"], 1.0],
    }


def _set_prior(value: float) -> Any:
    def change(manifest: dict[str, Any]) -> None:
        manifest["map_prior"] = {
            "config_sha256": manifest["config"]["sha256"],
            "recall_at_1": 0.5,
            "pseudo_queries": 40,
            "map_prior": value,
        }

    return change


def test_a_model_reading_the_map_prior_gets_the_versions_prior_or_refuses_it(
    service_index: Path, models: dict[str, Any], keys: dict[str, str], night: list[Path],
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    acc = _acceptance(models)
    acc["model"] = _with_offset(acc["model"])
    acc["sequence_model"] = _with_offset(acc["sequence_model"])
    root = tmp_path / "index"
    bare = _build_version(service_index, root, acc, with_map_prior=False)  # no prior stored
    monkeypatch.setenv("HMPF_AUTH", "false")
    _never_serve(monkeypatch)
    assert serve_main(["--index", str(root), "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "map_prior" in err and "hmpf-index build --map-prior" in err and "Traceback" not in err
    frames = [night[i] for i in TEST]
    logits = {}
    for value in (1.5, -2.0):
        _copy_with(root, bare, _set_prior(value))
        reader = IndexReader(root)
        try:
            assert reader.map_prior() == value
            profile = reader.reference_profile()
            model = reader.config.acceptance.confidence_model()  # type: ignore[union-attr]
            results = [
                reader.hierarchy().run(reader.scorer(reader.extract_query(_rgb(f))), reader.n)
                for f in frames
            ]
            feats = [answer_features(r, reader.route_map(), profile=profile) for r in results]
        finally:
            reader.close()
        assert all(f["map_prior"] == value for f in feats)
        with _client(root, keys) as c:
            served = [_post(c, keys, f)["match"] for f in frames]
            info = c.get("/v1/index", headers={"X-API-Key": keys["vehicle"]}).json()
        assert info["acceptance"]["map_prior"] == value
        assert info["acceptance"]["map_prior_stored"] is True
        p = np.array([m["p_correct"] for m in served])
        assert p == pytest.approx([model.predict(f) for f in feats], rel=1e-9, abs=1e-12)
        # hmpf-eval --index decides with the same prior: the same probabilities
        rep = evaluate_frames(root, frames, list(TEST), TOLERANCE)
        assert rep["acceptance"]["single"]["p_correct"] == pytest.approx(p, rel=1e-9, abs=1e-12)
        logits[value] = np.log(p) - np.log1p(-p)
    # an offset: the prior moves every answer's log-odds by exactly its own change
    assert logits[1.5] - logits[-2.0] == pytest.approx(np.full(len(frames), 3.5), abs=1e-6)

    # Models with a fallback serve a version without a prior as if it stored the fallback,
    # and say so; hmpf-eval --index decides alike.
    acc["map_prior_fallback"] = -2.0
    _build_version(service_index, root, acc, with_map_prior=False)
    with _client(root, keys) as c:
        served = [_post(c, keys, f)["match"] for f in frames]
        info = c.get("/v1/index", headers={"X-API-Key": keys["vehicle"]}).json()
    assert info["acceptance"]["map_prior"] == -2.0
    assert info["acceptance"]["map_prior_stored"] is False
    assert info["acceptance"]["map_prior_fallback"] == -2.0
    p = np.array([m["p_correct"] for m in served])
    assert np.log(p) - np.log1p(-p) == pytest.approx(logits[-2.0], abs=1e-9)
    rep = evaluate_frames(root, frames, list(TEST), TOLERANCE)
    assert rep["acceptance"]["single"]["p_correct"] == pytest.approx(p, rel=1e-9, abs=1e-12)


# -- a gated model: P(in map) x P(right | in map) ---------------------------------------------


def test_a_gated_model_is_served_as_the_product_of_its_parts(
    service_index: Path, models: dict[str, Any], keys: dict[str, str], night: list[Path],
    tmp_path: Path,
) -> None:  # fmt: skip
    """A version whose single-frame model has a gate (model format version 2, reading the
    hinge ``ref_z_low`` the service computes): each answer's p_correct is the gate's
    probability times the in-map part's, and hmpf-eval --index gives the same."""
    plain = models["model"].to_dict()
    inner = {
        **plain,
        "features": [*plain["features"], "ref_z_low"],
        "mean": [*plain["mean"], 0.0],
        "scale": [*plain["scale"], 1.0],
        "coef": [*plain["coef"], 0.5],
    }
    gate = ConfidenceModel(("ref_z", "ref_z_low"), (0.5, -0.2), (1.5, 0.5), (0.8, 1.5), 0.3)
    acc = _acceptance(models)
    acc["model"] = {**inner, "version": 2, "gate": gate.to_dict()}
    root = tmp_path / "index"
    _build_version(service_index, root, acc)
    frames = [night[i] for i in TEST]
    reader = IndexReader(root)
    try:
        profile, routes = reader.reference_profile(), reader.route_map()
        results = [
            reader.hierarchy().run(reader.scorer(reader.extract_query(_rgb(f))), reader.n)
            for f in frames
        ]
        feats = [answer_features(r, routes, profile=profile) for r in results]
    finally:
        reader.close()
    part = ConfidenceModel.from_dict(inner)
    want = [gate.predict(f) * part.predict(f) for f in feats]
    assert all(f["ref_z_low"] == min(f["ref_z"], 0.0) for f in feats)
    with _client(root, keys) as c:
        served = [_post(c, keys, f)["match"] for f in frames]
        info = c.get("/v1/index", headers={"X-API-Key": keys["vehicle"]}).json()
    p = [m["p_correct"] for m in served]
    assert p == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert [m["accepted"] for m in served] == [x >= models["threshold"] for x in p]
    assert info["acceptance"]["model"]["features"] == inner["features"]
    rep = evaluate_frames(root, frames, list(TEST), TOLERANCE)
    assert rep["acceptance"]["single"]["p_correct"] == pytest.approx(p, rel=1e-9, abs=1e-12)
