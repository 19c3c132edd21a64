"""A real ``hmpf-serve`` over an index version holding fleet experiences: answers name the
place (its original reference, position, route) and which stored image of it matched.

The index: 10 Gardens Point day_right places with positions; the served version adds
experiences (night_right and day_left frames of places 2, 5, 5 and 8) through the indexer's
own transaction (:func:`tests.hmpf.index.test_places.publish_experiences`).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from hmpf.config import parse_config
from indexer.build import build
from tests.conftest import BASE_LAT, BASE_LON, STEP_LAT, copy_gp, write_positions
from tests.hmpf.index.test_places import EXPERIENCES, publish_experiences
from tests.service_helpers import BUILD_OPTIONS, Server

P = 10
CONFIG = {
    "name": "experiences-service-test",
    "tiers": [{"methods": ["hog", "gist"], "k": 4}, {"methods": ["sad", "gist"], "k": 1}],
}


@pytest.fixture(scope="module")
def server(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    base = tmp_path_factory.mktemp("experiences")
    refs = copy_gp(gardens_point, "day_right", base / "refs", P)
    csv = write_positions(refs, base / "meta.csv")
    build(parse_config(CONFIG), refs, base / "index", metadata=csv, options=BUILD_OPTIONS)
    frames = [(sorted((gardens_point / t).iterdir())[i], pl) for t, i, pl in EXPERIENCES]
    publish_experiences(base / "index", frames, options=BUILD_OPTIONS)
    srv = Server(base / "index", base / "serve.log", auth="false")
    yield srv
    srv.stop()


def _localize(server: Server, image: Path, **data: Any) -> dict[str, Any]:
    headers = {}
    if "vehicle_id" in data:
        headers["X-Vehicle-Id"] = data.pop("vehicle_id")
    if "track" in data:
        headers["X-Track"] = data.pop("track")
    with image.open("rb") as fh:
        r = httpx.post(
            server.url + "/v1/localize",
            files={"image": (image.name, fh)},
            data=data,
            headers=headers,
            timeout=60,
        )
    assert r.status_code == 200, r.text
    body: dict[str, Any] = r.json()
    return body


def _frame(gardens_point: Path, traverse: str, i: int) -> Path:
    return sorted((gardens_point / traverse).iterdir())[i]


def test_answer_names_the_place_and_the_experience(server, gardens_point) -> None:
    place = _frame(gardens_point, "day_right", 5)
    body = _localize(server, _frame(gardens_point, "night_right", 5))
    m = body["match"]
    assert (m["reference_id"], m["name"]) == (5, place.name)
    assert m["lat"] == pytest.approx(BASE_LAT + 5 * STEP_LAT) and m["lon"] == BASE_LON
    e = m["experience"]
    assert e["row"] == P + 1 and not e["original"]
    assert e["name"].endswith("Image005.jpg") and e["name"] != place.name
    assert (e["vehicle"], e["log"], e["version"]) == ("car-7", "log-a", "v0001")
    assert (e["time"], e["p_correct"]) == (1.7e9 + 1, 0.995)
    assert body["index_version"] == "v0002"
    assert all(c["reference_id"] < P for c in body["candidates"])
    # The experience's own thumbnail is served by its row.
    r = httpx.get(f"{server.url}/v1/references/{e['row']}/thumbnail")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"


def test_an_original_reference_is_named_as_such(server, gardens_point) -> None:
    frame = _frame(gardens_point, "day_right", 3)
    m = _localize(server, frame)["match"]
    assert (m["reference_id"], m["name"]) == (3, frame.name)
    assert m["experience"] == {
        "row": 3,
        "name": frame.name,
        "original": True,
        "vehicle": None,
        "time": None,
        "p_correct": None,
        "log": None,
        "version": None,
    }


def test_gps_prior_and_index_count_places(server, gardens_point) -> None:
    body = _localize(
        server,
        _frame(gardens_point, "night_right", 8),
        lat=BASE_LAT + 8 * STEP_LAT,
        lon=BASE_LON,
        radius_m=30,
    )
    assert body["prior"]["applied"] and body["prior"]["references"] == 4  # places 6 .. 9
    m = body["match"]
    assert m["reference_id"] == 8 and m["experience"]["row"] == P + 3
    info = httpx.get(server.url + "/v1/index").json()
    assert info["references"] == P


def test_sequence_estimate_says_which_experience_matched(server, gardens_point) -> None:
    track = None
    for i in (4, 5):
        data: dict[str, Any] = {"vehicle_id": "car-9", "timestamp": float(i)}
        if track is not None:
            data["track"] = track
        body = _localize(server, _frame(gardens_point, "night_right", i), **data)
        track = body["sequence"]["track"]
    assert body["match_source"] == "sequence"
    est = body["sequence"]["match"]
    assert est["experience"] is not None and est["experience"]["row"] >= 0
    assert body["single"]["experience"]["row"] == P + 1
    if est["reference_id"] == 5:
        assert est["experience"]["row"] == P + 1
