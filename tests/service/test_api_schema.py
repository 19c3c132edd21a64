"""The OpenAPI document tells the truth: what each route takes (the limits the code enforces),
what it answers (media types, bodies, error codes) and who may see what.

The schema-driven fuzzing of a real server against this document is tests/service/test_fuzz.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.auth import add_key
from service.settings import load_settings

FIELDS = {"lat", "lon", "radius_m", "top_k", "vehicle_id", "track", "timestamp"}
#: The vehicle's id and track: headers or form fields, never query parameters (URLs are logged).
VEHICLE = {"vehicle_id": "X-Vehicle-Id", "track": "X-Track"}
MAX_TOP_K, MAX_BATCH, MAX_PIXELS = 7, 3, 1_000_000


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    path = tmp_path_factory.mktemp("schema-keys") / "keys.yaml"
    return {
        "file": path,
        "vehicle": {"X-API-Key": add_key(path, "car", "vehicle")},
        "admin": {"X-API-Key": add_key(path, "ops", "admin")},
    }


@pytest.fixture(scope="module")
def client(service_index: Path, keys: dict[str, Any]):
    settings = load_settings(
        None,
        index=service_index,
        keys_file=keys["file"],
        max_top_k=MAX_TOP_K,
        max_batch=MAX_BATCH,
        max_pixels=MAX_PIXELS,
        workers=1,
    )
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="module")
def doc(client: TestClient) -> dict[str, Any]:
    body: dict[str, Any] = client.get("/openapi.json").json()
    return body


def _deref(doc: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        schema = doc["components"]["schemas"][schema["$ref"].rsplit("/", 1)[-1]]
    return schema


def _non_null(schema: dict[str, Any]) -> dict[str, Any]:
    """The non-null branch of an ``anyOf: [X, null]`` (an optional field)."""
    for branch in schema.get("anyOf", [schema]):
        if branch.get("type") != "null":
            return branch
    raise AssertionError(schema)


def _form(doc: dict[str, Any], path: str) -> dict[str, Any]:
    body = doc["paths"][path]["post"]["requestBody"]["content"]["multipart/form-data"]
    return _deref(doc, body["schema"])


def _query(doc: dict[str, Any], path: str, where: str = "query") -> dict[str, dict[str, Any]]:
    params = doc["paths"][path]["post"]["parameters"]
    return {p["name"]: p["schema"] for p in params if p["in"] == where}


def _png(width: int, height: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((height, width, 3), 127, np.uint8))
    assert ok
    return buf.tobytes()


def test_metrics_is_documented_as_prometheus_text(client, doc) -> None:
    content = doc["paths"]["/metrics"]["get"]["responses"]["200"]["content"]
    assert set(content) == {"text/plain"}, content
    assert content["text/plain"]["schema"]["type"] == "string"
    assert client.get("/metrics").headers["content-type"].startswith("text/plain")


def test_health_answers_are_documented(doc) -> None:
    for path in ("/healthz", "/readyz"):
        ok = doc["paths"][path]["get"]["responses"]["200"]["content"]["application/json"]
        schema = _deref(doc, ok["schema"])
        assert schema["properties"]["status"] and "status" in schema["required"], path
    ready = _deref(doc, {"$ref": "#/components/schemas/Ready"})
    assert {"status", "index_version"} <= set(ready["properties"])
    assert "503" in doc["paths"]["/readyz"]["get"]["responses"]


@pytest.mark.parametrize("path", ["/v1/localize", "/v1/localize/batch"])
def test_every_enforced_field_limit_is_in_the_document(doc, path) -> None:
    """Query parameters and form fields of both routes, with the ranges the code enforces
    (top_k's maximum is this service's ``max_top_k``)."""
    query, form = _query(doc, path), _form(doc, path)["properties"]
    headers = {
        name: schema
        for name, schema in _query(doc, path, "header").items()
        if name in VEHICLE.values()
    }
    assert set(query) == FIELDS - set(VEHICLE) and FIELDS <= set(form)
    assert set(headers) == set(VEHICLE.values())
    for source in (query, form):
        assert source["top_k"]["minimum"] == 1 and source["top_k"]["maximum"] == MAX_TOP_K
        lat, lon = _non_null(source["lat"]), _non_null(source["lon"])
        assert (lat["minimum"], lat["maximum"]) == (-90, 90)
        assert (lon["minimum"], lon["maximum"]) == (-180, 180)
        assert _non_null(source["radius_m"])["exclusiveMinimum"] == 0
    for vehicle in (_non_null(form["vehicle_id"]), _non_null(headers["X-Vehicle-Id"])):
        assert (vehicle["minLength"], vehicle["maxLength"]) == (1, 128)
        # Spelled out, so that every regex dialect (JSON Schema's ECMA-262, Python's, Rust's)
        # reads the same characters: \w means Unicode letters to some and ASCII to others.
        assert vehicle["pattern"] == "^[A-Za-z0-9_.:@-]+$"


def test_image_limits_are_in_the_document(doc) -> None:
    single = _form(doc, "/v1/localize")["properties"]["image"]
    raw = doc["paths"]["/v1/localize"]["post"]["requestBody"]
    batch = _form(doc, "/v1/localize/batch")["properties"]["images"]
    assert (batch["minItems"], batch["maxItems"]) == (1, MAX_BATCH)
    for text in (single["description"], raw["description"], batch["description"]):
        assert "2 x 2" in text and f"{MAX_PIXELS} pixels" in text, text


def test_vehicle_id_outside_the_documented_characters_is_refused(client, keys) -> None:
    image = {"image": ("a.png", _png(64, 48), "image/png")}
    for bad in ("voiture-é", "car 1", "car/1", "x" * 129):
        r = client.post(
            "/v1/localize", files=image, data={"vehicle_id": bad}, headers=keys["admin"]
        )
        assert r.status_code == 422, (bad, r.text)
        assert "vehicle_id" in r.json()["error"]["message"]


def test_reload_documents_its_answer_and_409(doc) -> None:
    responses = doc["paths"]["/v1/index/reload"]["post"]["responses"]
    ok = _deref(doc, responses["200"]["content"]["application/json"]["schema"])
    assert set(ok["properties"]) == {"previous", "version", "changed"}
    assert set(ok["required"]) == {"previous", "version", "changed"}
    conflict = responses["409"]["content"]["application/json"]["schema"]
    assert conflict == {"$ref": "#/components/schemas/ErrorBody"}


def test_each_operation_documents_the_errors_it_answers(doc) -> None:
    def codes(path: str, method: str) -> set[str]:
        return set(doc["paths"][path][method]["responses"]) - {"200"}

    for path in ("/v1/localize", "/v1/localize/batch"):
        assert codes(path, "post") == {"401", "403", "413", "415", "422", "503"}, path
    assert codes("/v1/index", "get") == {"401", "403"}
    assert codes("/v1/index/reload", "post") == {"401", "403", "409"}
    assert codes("/readyz", "get") == {"503"}
    for path, method in (("/v1/index", "get"), ("/v1/index/reload", "post")):
        for code in codes(path, method):
            body = doc["paths"][path][method]["responses"][code]["content"]["application/json"]
            assert body["schema"] == {"$ref": "#/components/schemas/ErrorBody"}


def test_index_paths_and_packages_are_for_admin_keys_only(client, keys, doc) -> None:
    vehicle = client.get("/v1/index", headers=keys["vehicle"])
    admin = client.get("/v1/index", headers=keys["admin"])
    assert vehicle.status_code == admin.status_code == 200
    seen, full = vehicle.json(), admin.json()
    assert seen["root"] is None and seen["built"]["packages"] is None
    assert Path(full["root"]).is_absolute() and full["built"]["packages"]["numpy"]
    assert str(full["root"]) not in vehicle.text
    # everything else is the same for both
    for body in (seen, full):
        body.pop("root")
        body["built"].pop("packages")
    assert seen == full
    info = _deref(doc, {"$ref": "#/components/schemas/IndexInfo"})
    assert "admin" in info["properties"]["root"]["description"]
    built = _deref(doc, info["properties"]["built"])
    assert "admin" in built["properties"]["packages"]["description"]


def test_index_info_without_auth_shows_everything(service_index: Path) -> None:
    """Without keys every caller may reload, as an admin: it sees what an admin sees."""
    settings = load_settings(None, index=service_index, auth=False, workers=1)
    with TestClient(create_app(settings)) as c:
        body = c.get("/v1/index").json()
    assert body["root"] == str(service_index) and body["built"]["packages"]


@pytest.mark.parametrize("path", ["/v1/localize", "/v1/localize/batch"])
def test_optional_fields_are_omitted_not_null(client, keys, doc, path) -> None:
    """A query parameter or form field has no null: an optional one is left out. The document
    does not offer null (found by the fuzzer: it sent ``timestamp=null`` and got a 422)."""
    query, form = _query(doc, path), _form(doc, path)["properties"]
    query |= {f: _query(doc, path, "header")[h] for f, h in VEHICLE.items()}
    for name in FIELDS:
        for schema in (query[name], form[name]):
            assert "anyOf" not in schema and schema.get("type") != "null", (name, schema)
            assert schema["description"], name
    assert _query(doc, path)["lat"]["type"] == "number"
    files = {"image" if path == "/v1/localize" else "images": ("a.png", _png(64, 48))}
    r = client.post(path, files=files, data={"timestamp": "null"}, headers=keys["admin"])
    assert r.status_code == 422
