"""The HTTP API through FastAPI's TestClient: every endpoint, every error, auth, the GPS prior.

The index is real (built from 20 Gardens Point images with positions); so are the images.
"""

from __future__ import annotations

import asyncio
import io
import json
import shutil
import struct
import threading
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from hmpf.datasets import haversine_m
from service.app import create_app
from service.auth import add_key
from service.settings import load_settings
from tests.conftest import BASE_LAT, BASE_LON, STEP_LAT
from tests.service_helpers import nan_in_final_tier


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    path = tmp_path_factory.mktemp("keys") / "keys.yaml"
    return {
        "file": path,
        "vehicle": add_key(path, "car-1", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


def _client(index: Path, keys_file: Path, **overrides: object) -> TestClient:
    settings = load_settings(
        None,
        index=index,
        keys_file=keys_file,
        max_upload_bytes=2 * 2**20,
        max_pixels=2_000_000,
        max_batch=4,
        workers=1,
        queue=2,
        **overrides,
    )
    return TestClient(create_app(settings))


@pytest.fixture(scope="module")
def client(service_index: Path, keys: dict[str, object]):
    with _client(service_index, keys["file"]) as c:  # type: ignore[arg-type]
        yield c


@pytest.fixture(scope="module")
def car(keys: dict[str, object]) -> dict[str, str]:
    return {"X-API-Key": str(keys["vehicle"])}


@pytest.fixture(scope="module")
def admin(keys: dict[str, object]) -> dict[str, str]:
    return {"X-API-Key": str(keys["admin"])}


def _ref(gardens_point: Path, i: int) -> Path:
    return sorted((gardens_point / "day_right").iterdir())[i]


def _error(r, status: int, code: str) -> dict[str, str]:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"} and body["error"]["code"] == code, body
    assert body["error"]["message"]
    return body["error"]


def _png(width: int, height: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros((height, width, 3), np.uint8))
    assert ok
    return buf.tobytes()


# -- health, docs, index info ------------------------------------------------------------------
def test_health_ready_docs(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["index_version"] == "v0001"
    assert "swagger" in client.get("/docs").text.lower()
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/v1/localize", "/v1/localize/batch", "/v1/index", "/v1/index/reload"):
        assert p in paths
    body = paths["/v1/localize"]["post"]["requestBody"]["content"]
    assert {"multipart/form-data", "image/jpeg", "image/png", "image/webp"} <= set(body)


def test_openapi_describes_the_key_and_every_body_the_code_accepts(
    client, car, gardens_point
) -> None:
    doc = client.get("/openapi.json").json()
    schemes = doc["components"]["securitySchemes"]
    ((scheme_name, scheme),) = schemes.items()
    assert scheme == {**scheme, "type": "apiKey", "in": "header", "name": "X-API-Key"}
    paths = doc["paths"]
    for path, method in (
        ("/v1/localize", "post"),
        ("/v1/localize/batch", "post"),
        ("/v1/index", "get"),
        ("/v1/index/reload", "post"),
    ):
        assert paths[path][method]["security"] == [{scheme_name: []}], path
    for path in ("/healthz", "/readyz", "/metrics"):
        assert "security" not in paths[path]["get"], path

    def form_schema(path: str) -> dict:
        body = paths[path]["post"]["requestBody"]
        ref = body["content"]["multipart/form-data"]["schema"]["$ref"]
        return doc["components"]["schemas"][ref.rsplit("/", 1)[-1]]

    fields = {"lat", "lon", "radius_m", "top_k", "vehicle_id", "track", "timestamp"}
    single, batch = form_schema("/v1/localize"), form_schema("/v1/localize/batch")
    assert set(single["properties"]) == fields | {"image"} and single["required"] == ["image"]
    assert set(batch["properties"]) == fields | {"images"} and batch["required"] == ["images"]
    assert batch["properties"]["images"]["type"] == "array"
    params = paths["/v1/localize"]["post"]["parameters"]
    query = {p["name"] for p in params if p["in"] == "query"}
    assert query == fields - {"vehicle_id", "track"}  # headers or form: URLs are logged
    assert {"X-Vehicle-Id", "X-Track"} <= {p["name"] for p in params if p["in"] == "header"}

    # Every documented way in is answered: the form with all its fields, and the raw body
    # under each documented content type.
    path = _ref(gardens_point, 8)
    r = client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        data={
            "lat": "-27.4762",
            "lon": "153.028",
            "radius_m": "50",
            "top_k": "2",
            "vehicle_id": "v",
        },
        headers=car,
    )
    assert r.status_code == 200, r.text
    raw_types = set(paths["/v1/localize"]["post"]["requestBody"]["content"]) - {
        "multipart/form-data"
    }
    assert {"image/jpeg", "image/png", "image/webp", "application/octet-stream"} <= raw_types
    for ctype in sorted(raw_types):
        assert paths["/v1/localize"]["post"]["requestBody"]["content"][ctype]["schema"] == {
            "type": "string",
            "format": "binary",
        }
        r = client.post(
            "/v1/localize?top_k=1",
            content=path.read_bytes(),
            headers={**car, "Content-Type": ctype},
        )
        assert r.status_code == 200, (ctype, r.text)
        assert r.json()["match"]["name"] == path.name


def test_nan_quality_is_reported_as_null_and_never_accepted(service_index, gardens_point) -> None:
    """A method that scores NaN for a final candidate makes the Combined z-scores NaN: the
    answer says so (null), rather than a z-value of 0.0, and does not accept the match."""
    from service.answer import localize_response
    from service.engine import Loaded
    from service.schemas import LocalizeParams

    loaded = Loaded.open(service_index, threshold=-100.0)  # any finite score is accepted
    try:
        image = cv2.cvtColor(cv2.imread(str(_ref(gardens_point, 4))), cv2.COLOR_BGR2RGB)
        real = loaded.reader.scorer(loaded.reader.extract_query(image))
        result = loaded.hierarchy.run(nan_in_final_tier(real), loaded.reader.n)
        assert np.isnan(result.quality) and result.match >= 0
        answer = localize_response(loaded, result, None, LocalizeParams(), {"total": 1.0})
    finally:
        loaded.reader.close()
    assert answer.match is not None
    assert answer.match.score is None and answer.match.accepted is False
    body = json.loads(
        answer.model_dump_json(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}")
    )
    assert body["match"]["score"] is None and body["match"]["accepted"] is False
    assert all(c["score"] is None for c in body["candidates"])


def test_index_info(client: TestClient, car: dict[str, str]) -> None:
    info = client.get("/v1/index", headers=car).json()
    assert info["version"] == "v0001" and info["versions"] == ["v0001"]
    assert info["references"] == 20
    assert set(info["methods"]) == {"hog", "gist", "sad"}
    assert info["config"]["name"] == "service-test"
    assert info["built"]["created"] and info["built"]["images_per_s"] > 0
    assert info["has_positions"] is True


# -- localisation ------------------------------------------------------------------------------
def test_localize_reference_image_finds_itself(client, car, gardens_point) -> None:
    path = _ref(gardens_point, 7)
    r = client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        data={"top_k": "3", "vehicle_id": "car-1"},
        headers=car,
    )
    assert r.status_code == 200, r.text
    body = r.json()
    # With a vehicle_id the answer may be the sequence estimate; the single-frame match is
    # reported on its own (test_service_sequence.py covers sequence mode).
    assert body["match"]["name"] == path.name and body["sequence"]["status"] == "started"
    m = body["single"]
    assert m["name"] == path.name and m["reference_id"] == 7
    assert m["lat"] == pytest.approx(BASE_LAT + 7 * STEP_LAT, abs=1e-6)
    assert m["lon"] == pytest.approx(BASE_LON, abs=1e-6)
    assert 0.0 <= m["confidence"] <= 1.0
    assert m["accepted"] == (m["score"] >= body["threshold"])
    assert body["index_version"] == "v0001" and body["vehicle_id"] == "car-1"
    assert [c["name"] for c in body["candidates"]][0] == path.name
    assert len(body["candidates"]) == 3
    scores = [c["score"] for c in body["candidates"]]
    assert scores == sorted(scores, reverse=True)
    tiers = body["tiers"]
    assert [t["methods"] for t in tiers] == [["hog", "gist"], ["gist", "sad"]]
    assert tiers[0]["inputs"] == 20 and tiers[1]["inputs"] == len(tiers[0]["candidates"])
    for t in tiers:
        for c in t["candidates"]:
            assert set(c["scores"]) == set(t["methods"])
            assert all(0.0 <= v <= 1.0 for v in c["scores"].values())
    timing = body["timing_ms"]
    for stage in ("queue", "decode", "extract", "hierarchy", "total"):
        assert timing[stage] >= 0.0
    assert set(timing["extract_per_method"]) == {"hog", "gist", "sad"}
    assert timing["total"] >= timing["extract"]


def test_localize_raw_body_and_every_format(client, car, gardens_point) -> None:
    path = _ref(gardens_point, 12)
    image = cv2.imread(str(path))
    answers = []
    raw = client.post(
        "/v1/localize?top_k=2",
        content=path.read_bytes(),
        headers={**car, "Content-Type": "image/jpeg"},
    )
    answers.append(raw)
    for ext, ctype in ((".png", "image/png"), (".webp", "image/webp")):
        ok, buf = cv2.imencode(
            ext, image, [cv2.IMWRITE_WEBP_QUALITY, 101] if ext == ".webp" else []
        )
        assert ok
        answers.append(
            client.post(
                "/v1/localize", files={"image": ("f" + ext, buf.tobytes(), ctype)}, headers=car
            )
        )
    for r in answers:
        assert r.status_code == 200, r.text
        assert r.json()["match"]["name"] == path.name
    assert len(answers[0].json()["candidates"]) == 2


def test_gps_prior_limits_candidates(client, car, gardens_point) -> None:
    path = _ref(gardens_point, 10)
    lat = BASE_LAT + 10 * STEP_LAT
    r = client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        data={"lat": str(lat), "lon": str(BASE_LON), "radius_m": "25", "top_k": "50"},
        headers=car,
    )
    assert r.status_code == 200, r.text
    body = r.json()
    lats = BASE_LAT + np.arange(20) * STEP_LAT
    inside = set(np.flatnonzero(haversine_m(lat, BASE_LON, lats, np.full(20, BASE_LON)) <= 25))
    assert 3 <= len(inside) < 20
    assert body["prior"]["applied"] is True and body["prior"]["references"] == len(inside)
    assert body["match"]["reference_id"] == 10
    assert {c["reference_id"] for c in body["candidates"]} <= inside
    assert body["tiers"][0]["inputs"] == len(inside)
    for t in body["tiers"]:
        assert {c["reference_id"] for c in t["candidates"]} <= inside

    # A prior far from every reference: no candidate, no match, still a 200.
    far = client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        params={"lat": "48.0", "lon": "11.0", "radius_m": "500"},
        headers=car,
    )
    assert far.status_code == 200, far.text
    assert far.json()["match"] is None and far.json()["prior"]["references"] == 0


def test_batch_answers_in_order_with_per_item_errors(client, car, gardens_point) -> None:
    a, b = _ref(gardens_point, 3), _ref(gardens_point, 15)
    files = [
        ("images", (a.name, a.read_bytes(), "image/jpeg")),
        ("images", ("junk.jpg", b"\xff\xd8\xff\xe0 not really a jpeg", "image/jpeg")),
        ("images", (b.name, b.read_bytes(), "image/jpeg")),
    ]
    r = client.post("/v1/localize/batch", files=files, data={"top_k": "1"}, headers=car)
    assert r.status_code == 200, r.text
    results = r.json()["results"]
    assert [x["index"] for x in results] == [0, 1, 2]
    assert results[0]["result"]["match"]["name"] == a.name
    assert (
        results[1]["error"]["code"] == "invalid_image"
        and "images[1]" in results[1]["error"]["message"]
    )
    assert results[2]["result"]["match"]["name"] == b.name
    assert r.json()["index_version"] == "v0001"


def test_batch_errors(client, car, gardens_point) -> None:
    a = _ref(gardens_point, 3).read_bytes()
    five = [("images", (f"{i}.jpg", a, "image/jpeg")) for i in range(5)]
    _error(client.post("/v1/localize/batch", files=five, headers=car), 422, "invalid_request")
    _error(
        client.post(
            "/v1/localize/batch", data={"top_k": "2"}, files=[("other", ("x", a))], headers=car
        ),
        422,
        "invalid_request",
    )
    for ctype in ("image/jpeg", "application/x-www-form-urlencoded"):
        _error(
            client.post("/v1/localize/batch", content=a, headers={**car, "Content-Type": ctype}),
            415,
            "unsupported_media_type",
        )


def test_batch_larger_than_the_admission_limit_runs_in_lanes(client, car, gardens_point) -> None:
    engine = client.app.state.engine  # workers=1, queue=2: 3 slots; max_batch=4
    paths = [_ref(gardens_point, i) for i in (2, 6, 11, 17)]
    files = [("images", (p.name, p.read_bytes(), "image/jpeg")) for p in paths]
    assert engine.admit(engine.capacity - 1)  # other queries hold all slots but one
    try:
        r = client.post("/v1/localize/batch", files=files, data={"top_k": "1"}, headers=car)
        assert r.status_code == 200, r.text
        assert [x["result"]["match"]["name"] for x in r.json()["results"]] == [
            p.name for p in paths
        ]
        assert engine.admit(1)  # the last slot is taken too: the batch is refused
        try:
            _error(client.post("/v1/localize/batch", files=files, headers=car), 503, "overloaded")
        finally:
            engine.done(1)
    finally:
        engine.done(engine.capacity - 1)
    assert engine.admitted == 0 and engine.running == 0


def test_batch_item_failing_unexpectedly_gets_its_own_error(
    client, car, gardens_point, monkeypatch
) -> None:
    import service.query as query_module

    real = query_module.decode_upload

    def flaky(data: bytes, **kw: object) -> np.ndarray:
        if data.startswith(b"BOOM"):
            raise RuntimeError("a bug, not the client's fault")
        return real(data, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(query_module, "decode_upload", flaky)
    a = _ref(gardens_point, 5)
    files = [
        ("images", ("boom.jpg", b"BOOM", "image/jpeg")),
        ("images", (a.name, a.read_bytes(), "image/jpeg")),
    ]
    r = client.post("/v1/localize/batch", files=files, data={"top_k": "1"}, headers=car)
    assert r.status_code == 200, r.text
    first, second = r.json()["results"]
    assert first["error"] == {"code": "internal", "message": "internal error"}
    assert second["result"]["match"]["name"] == a.name
    # The same failure in a single query is a generic JSON 500, the traceback only in the log.
    plain = TestClient(client.app, raise_server_exceptions=False)  # as a real client sees it
    one = plain.post("/v1/localize", files={"image": ("b.jpg", b"BOOM", "image/jpeg")}, headers=car)
    assert one.status_code == 500 and "a bug" not in one.text
    assert one.json()["error"]["code"] == "internal"
    engine = client.app.state.engine
    assert engine.admitted == 0 and engine.current.leases == 0


def _wait_for(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_a_cancelled_request_frees_its_slot_and_lease_only_when_the_work_ends(client) -> None:
    engine = client.app.state.engine  # one query thread
    gate, started, ran = threading.Event(), threading.Event(), []

    def blocking(loaded) -> str:
        started.set()
        gate.wait(10)
        return str(loaded.version)

    def queued(loaded) -> str:
        ran.append(1)
        return str(loaded.version)

    async def cancel_both() -> None:
        assert engine.admit(2)
        first = asyncio.ensure_future(engine.run([blocking]))
        second = asyncio.ensure_future(engine.run([queued]))  # waits for the only thread
        assert await asyncio.to_thread(started.wait, 10)
        first.cancel()
        second.cancel()
        for task in (first, second):
            with pytest.raises(asyncio.CancelledError):
                await task

    asyncio.run(cancel_both())
    # The waiting query never ran and gave its slot back; the running one still holds its
    # slot and its lease on the version although its request is gone.
    assert engine.admitted == 1 and engine.current.leases == 1 and engine.running == 1
    gate.set()
    assert _wait_for(lambda: engine.admitted == 0 and engine.current.leases == 0)
    assert ran == [] and engine.running == 0


# -- auth --------------------------------------------------------------------------------------
def test_auth(client, car, admin, gardens_point) -> None:
    image = {"image": ("a.jpg", _ref(gardens_point, 1).read_bytes(), "image/jpeg")}
    r = client.post("/v1/localize", files=image)
    _error(r, 401, "unauthorized")
    assert r.headers["www-authenticate"] == "ApiKey"
    _error(
        client.post("/v1/localize", files=image, headers={"X-API-Key": "nope"}), 401, "unauthorized"
    )
    _error(client.get("/v1/index"), 401, "unauthorized")
    _error(client.post("/v1/index/reload", headers=car), 403, "forbidden")
    assert client.post("/v1/localize", files=image, headers=admin).status_code == 200
    assert client.get("/v1/index", headers=admin).status_code == 200
    r = client.post("/v1/index/reload", headers=admin)
    assert r.status_code == 200 and r.json() == {
        "previous": "v0001",
        "version": "v0001",
        "changed": False,
    }
    for open_route in ("/healthz", "/readyz", "/metrics"):
        assert client.get(open_route).status_code == 200
    # Without a key, what is wrong with the body is not the answer: 401 comes first.
    for route in ("/v1/localize", "/v1/localize/batch"):
        bad = client.post(route, content=b"x", headers={"Content-Type": "multipart/form-data"})
        _error(bad, 401, "unauthorized")
        fields = client.post(route, files=image, data={"top_k": "abc"})
        _error(fields, 401, "unauthorized")

    def chunks():  # streamed past the limit, without Content-Length
        yield b"--b\r\nContent-Disposition: form-data; name=image; filename=a.jpg\r\n\r\n"
        for _ in range(48):
            yield bytes(128 * 1024)

    streamed = client.post(
        "/v1/localize",
        content=chunks(),
        headers={"Content-Type": "multipart/form-data; boundary=b"},
    )
    _error(streamed, 401, "unauthorized")


# -- bad input ---------------------------------------------------------------------------------
def test_upload_size_limits(client, car, gardens_point) -> None:
    big = b"\xff\xd8\xff" + bytes(3 * 2**20)
    # Declared Content-Length over the limit: refused before reading.
    _error(
        client.post("/v1/localize", content=big, headers={**car, "Content-Type": "image/jpeg"}),
        413,
        "payload_too_large",
    )

    # No Content-Length (chunked): refused once the limit is crossed (the end-to-end test
    # checks that a real server answers before the body has been sent in full).
    def chunks():
        for _ in range(48):
            yield bytes(128 * 1024)

    r = client.post("/v1/localize", content=chunks(), headers={**car, "Content-Type": "image/jpeg"})
    _error(r, 413, "payload_too_large")
    # multipart, streamed
    r = client.post(
        "/v1/localize",
        files={"image": ("big.jpg", io.BytesIO(big), "image/jpeg")},
        headers=car,
    )
    _error(r, 413, "payload_too_large")


def test_decompression_bomb_is_refused_from_the_header(client, car) -> None:
    bomb = _png(2000, 1500)  # 3 M pixels, a few KB on the wire
    assert len(bomb) < 100_000
    err = _error(
        client.post("/v1/localize", files={"image": ("b.png", bomb, "image/png")}, headers=car),
        413,
        "too_many_pixels",
    )
    assert "2000 x 1500" in err["message"]
    # A header claiming 50000 x 50000 in a 60-byte file: refused without decoding.
    ihdr = struct.pack(">IIBBBBB", 50000, 50000, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    fake = b"\x89PNG\r\n\x1a\n" + chunk
    _error(
        client.post("/v1/localize", content=fake, headers={**car, "Content-Type": "image/png"}),
        413,
        "too_many_pixels",
    )


@pytest.mark.parametrize(
    ("content", "ctype", "status", "code"),
    [
        (b"GIF89a" + bytes(64), "image/gif", 415, "unsupported_media_type"),
        (b"GIF89a" + bytes(64), "image/jpeg", 415, "unsupported_media_type"),
        (b"BM" + bytes(64), "application/octet-stream", 415, "unsupported_media_type"),
        (b"hello", "text/plain", 415, "unsupported_media_type"),
        (b"hello", None, 415, "unsupported_media_type"),
        (b"", "image/jpeg", 422, "invalid_image"),
        (b"definitely not an image", "image/jpeg", 422, "invalid_image"),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "image/jpeg", 422, "invalid_image"),
    ],
)
def test_bad_image_bodies(client, car, content, ctype, status, code) -> None:
    headers = dict(car)
    if ctype:
        headers["Content-Type"] = ctype
    _error(client.post("/v1/localize", content=content, headers=headers), status, code)


def test_truncated_and_damaged_images(client, car, gardens_point) -> None:
    data = _ref(gardens_point, 2).read_bytes()
    for blob in (data[: len(data) // 2], data[:600]):
        _error(
            client.post(
                "/v1/localize", files={"image": ("t.jpg", blob, "image/jpeg")}, headers=car
            ),
            422,
            "invalid_image",
        )
    png = _png(64, 48)
    _error(
        client.post(
            "/v1/localize", files={"image": ("t.png", png[:-30], "image/png")}, headers=car
        ),
        422,
        "invalid_image",
    )


@pytest.mark.parametrize(
    ("fields", "params", "needle"),
    [
        ({"top_k": "abc"}, {}, "top_k"),
        ({"top_k": "0"}, {}, "top_k"),
        ({"top_k": "51"}, {}, "top_k"),
        ({}, {"top_k": "-3"}, "top_k"),
        ({"lat": "10"}, {}, "lat, lon and radius_m"),
        ({"lat": "95", "lon": "0", "radius_m": "10"}, {}, "lat"),
        ({"lat": "1", "lon": "1", "radius_m": "-5"}, {}, "radius_m"),
        ({"vehicle_id": "a b"}, {}, "vehicle_id"),
        ({"color": "red"}, {}, "color"),
        ({"top_k": "2"}, {"top_k": "3"}, "given twice"),
        ({}, [("top_k", "2"), ("top_k", "3")], "given twice"),
        ({}, {"color": "red"}, "color"),
        ({"lat": "10"}, {"lon": "10"}, "lat, lon and radius_m"),
    ],
)
def test_malformed_fields(client, car, gardens_point, fields, params, needle) -> None:
    image = {"image": ("a.jpg", _ref(gardens_point, 1).read_bytes(), "image/jpeg")}
    r = client.post("/v1/localize", files=image, data=fields, params=params, headers=car)
    assert needle in _error(r, 422, "invalid_request")["message"]


def test_malformed_requests(client, car, gardens_point) -> None:
    data = _ref(gardens_point, 1).read_bytes()
    # no image field, two image fields, a broken multipart body
    _error(
        client.post("/v1/localize", data={"top_k": "2"}, files={"other": ("a", data)}, headers=car),
        422,
        "invalid_request",
    )
    two = [("image", ("a.jpg", data, "image/jpeg")), ("image", ("b.jpg", data, "image/jpeg"))]
    _error(client.post("/v1/localize", files=two, headers=car), 422, "invalid_request")
    r = client.post(
        "/v1/localize",
        content=b'--xyz\r\nContent-Disposition: form-data; name="image"\r\n\r\nabc',
        headers={**car, "Content-Type": "multipart/form-data; boundary=xyz"},
    )
    assert r.status_code == 422 and "error" in r.json()
    # A body the multipart parser cannot read is a 422 like any invalid request, not a 400.
    for route in ("/v1/localize", "/v1/localize/batch"):
        r = client.post(
            route, content=b"no parts", headers={**car, "Content-Type": "multipart/form-data"}
        )
        assert "malformed multipart body" in _error(r, 422, "invalid_request")["message"]
    # A text field where a file belongs.
    _error(
        client.post("/v1/localize", files={"image": (None, "abc")}, headers=car),
        422,
        "invalid_request",
    )
    _error(client.get("/v1/localize", headers=car), 405, "method_not_allowed")
    _error(client.get("/v1/nothing-here", headers=car), 404, "not_found")


def test_overload_answers_503_with_retry_after(client, car, gardens_point) -> None:
    engine = client.app.state.engine
    assert engine.admit(engine.capacity)  # every slot taken, as by long-running queries
    try:
        image = {"image": ("a.jpg", _ref(gardens_point, 1).read_bytes(), "image/jpeg")}
        r = client.post("/v1/localize", files=image, headers=car)
        _error(r, 503, "overloaded")
        assert r.headers["retry-after"] == "1"
    finally:
        engine.done(engine.capacity)
    assert client.post("/v1/localize", files=image, headers=car).status_code == 200


def test_metrics(client, car, gardens_point) -> None:
    r = client.post(
        "/v1/localize", files={"image": ("a.jpg", _ref(gardens_point, 4).read_bytes())}, headers=car
    )
    assert r.status_code == 200, r.text
    client.get("/v1/index")  # 401
    text = client.get("/metrics").text
    assert 'hmpf_requests_total{method="POST",route="/v1/localize",status="200"}' in text
    assert 'hmpf_requests_total{method="GET",route="/v1/index",status="401"}' in text
    for stage in ("queue", "decode", "extract", "hierarchy", "total"):
        assert f'hmpf_stage_seconds_count{{stage="{stage}"}}' in text
    assert 'hmpf_index_info{version="v0001"} 1.0' in text
    assert "hmpf_queue_depth" in text and "hmpf_request_seconds_bucket" in text
    # A made-up HTTP method does not become a label value of its own.
    assert client.request("BREW", "/healthz").status_code == 405
    text = client.get("/metrics").text
    assert 'method="other",route="/healthz",status="405"' in text and "BREW" not in text


# -- reload ------------------------------------------------------------------------------------
def test_reload_switches_versions_and_keeps_a_good_one(
    service_index, keys, admin, car, gardens_point, tmp_path
) -> None:
    from indexer.build import BuildOptions, remove

    index = tmp_path / "index"
    shutil.copytree(service_index, index)
    with _client(index, keys["file"]) as c:  # type: ignore[arg-type]
        remove(index, ["Image000.jpg"], options=BuildOptions(workers=1, progress=False))
        r = c.post("/v1/index/reload", headers=admin)
        assert r.json() == {"previous": "v0001", "version": "v0002", "changed": True}
        info = c.get("/v1/index", headers=car).json()
        assert info["version"] == "v0002" and info["references"] == 19
        path = _ref(gardens_point, 9)
        body = c.post(
            "/v1/localize", files={"image": (path.name, path.read_bytes())}, headers=car
        ).json()
        assert body["index_version"] == "v0002" and body["match"]["name"] == path.name

        # A current version that cannot be opened: 409, the loaded one stays in service.
        (index / "v0002" / "manifest.json").write_text("{ broken")
        _error(c.post("/v1/index/reload", headers=admin), 409, "index_unusable")
        body = c.post(
            "/v1/localize", files={"image": (path.name, path.read_bytes())}, headers=car
        ).json()
        assert body["index_version"] == "v0002"
        assert c.get("/readyz").json()["index_version"] == "v0002"


def test_auth_off_needs_an_explicit_setting(service_index, gardens_point, caplog) -> None:
    with pytest.raises(Exception, match="HMPF_AUTH=false"):
        load_settings(None, index=service_index)
    settings = load_settings(None, index=service_index, auth=False, workers=1)
    with caplog.at_level("WARNING"), TestClient(create_app(settings)) as c:
        path = _ref(gardens_point, 5)
        assert (
            c.post("/v1/localize", files={"image": (path.name, path.read_bytes())}).status_code
            == 200
        )
    assert any("authentication is OFF" in r.getMessage() for r in caplog.records)


def test_response_is_json_serialisable_without_nan(client, car, gardens_point) -> None:
    r = client.post(
        "/v1/localize", files={"image": ("a.jpg", _ref(gardens_point, 0).read_bytes())}, headers=car
    )
    assert r.status_code == 200, r.text
    json.loads(r.text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))


def test_acceptance_threshold_sources(service_index, keys, car, gardens_point, tmp_path) -> None:
    """settings > the index config's acceptance.threshold > the built-in default."""
    from hmpf.config import parse_config
    from indexer.build import BuildOptions, build
    from service.engine import DEFAULT_ACCEPT_THRESHOLD
    from tests.conftest import SERVICE_CONFIG

    path = _ref(gardens_point, 6)
    files = {"image": (path.name, path.read_bytes(), "image/jpeg")}

    def answer(index: Path, **overrides: object) -> dict:
        with _client(index, keys["file"], **overrides) as c:  # type: ignore[arg-type]
            r = c.post("/v1/localize", files=files, headers=car)
            assert r.status_code == 200, r.text
            return r.json()

    body = answer(service_index)
    assert body["threshold"] == DEFAULT_ACCEPT_THRESHOLD
    assert body["match"]["accepted"] == (body["match"]["score"] >= DEFAULT_ACCEPT_THRESHOLD)
    low = answer(service_index, accept_threshold=-100.0)
    assert low["threshold"] == -100.0 and low["match"]["accepted"] is True

    refs = tmp_path / "refs"
    refs.mkdir()
    for p in sorted((gardens_point / "day_right").iterdir())[:8]:
        shutil.copy(p, refs / p.name)
    cfg = parse_config({**SERVICE_CONFIG, "acceptance": {"threshold": 99.0, "precision": 0.99}})
    build(cfg, refs, tmp_path / "index", options=BuildOptions(workers=1, progress=False))
    strict = answer(tmp_path / "index")
    assert strict["threshold"] == 99.0 and strict["match"]["accepted"] is False
    assert answer(tmp_path / "index", accept_threshold=0.5)["threshold"] == 0.5
