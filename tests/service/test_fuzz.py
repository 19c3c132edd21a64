"""Schema-driven fuzzing (Schemathesis) of a real ``hmpf-serve`` (uvicorn on loopback, over a
small real index) against its own OpenAPI document.

Every operation of ``/openapi.json`` gets requests generated from the document: valid ones and,
in negative mode, ones that break it (out-of-range numbers, unknown fields, wrong types, no
key). A run fails on any 5xx, on a status code, content type or body the document does not
declare, on invalid input that is not refused with a 4xx, and on a route that answers without
its key; valid requests (with a real frame, see :func:`_follow_the_rules_in_words`) must be
answered 2xx. The generation is seeded and the number of examples per operation fixed
(:data:`MAX_EXAMPLES` in the fuzzing phase, besides the examples and coverage phases' own
cases), so the run is bounded: about 550 requests, 10-20 s on two cores.
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import pytest
import schemathesis
from schemathesis import GenerationMode

from service.app import create_app
from service.auth import add_key
from service.settings import load_settings
from tests.service_helpers import Server

#: Hypothesis examples per operation in the fuzzing phase (valid and invalid together).
MAX_EXAMPLES = 25
#: The served limits (small, so that the fuzzer reaches them).
LIMITS = {
    "workers": 1,
    "queue": 8,
    "max_batch": 3,
    "max_top_k": 10,
    "max_upload_bytes": 262144,
    "max_pixels": 1_000_000,
}
#: Requests sent, per operation and status (a summary, and a check that the run happened).
SENT: Counter[tuple[str, int]] = Counter()
#: The document, generated in process from the settings the server runs with (the schema
#: must be known when the tests are collected; the server's own /openapi.json is checked to
#: be this one before any request is fuzzed).
DOCUMENT = create_app(load_settings(None, auth=False, **LIMITS)).openapi()
CONFIG = schemathesis.Config.from_dict(
    {
        "seed": 23,
        # no example database: each run is the same, seeded one (no .hypothesis/examples)
        "generation": {"mode": "all", "max-examples": MAX_EXAMPLES, "database": "none"},
        "phases": {"stateful": {"enabled": False}},
        "request-timeout": 60,
    }
)
schema = schemathesis.openapi.from_dict(DOCUMENT, config=CONFIG)
# image/jpg (a common misspelling the service accepts) is sent like image/jpeg
schemathesis.serializer.alias("image/jpg", "image/jpeg")
DOCUMENT_OPERATIONS = [(m, p) for p, ops in DOCUMENT["paths"].items() for m in ops]


@pytest.fixture(scope="module")
def admin_key(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    path = tmp_path_factory.mktemp("fuzz-keys") / "keys.yaml"
    return path, add_key(path, "ops", "admin")


@pytest.fixture(scope="module")
def server(service_index: Path, admin_key, tmp_path_factory) -> Iterator[Server]:
    log = tmp_path_factory.mktemp("fuzz-log") / "serve.log"
    env = {k: str(v) for k, v in LIMITS.items()}
    srv = Server(service_index, log, keys_file=str(admin_key[0]), **env)
    assert httpx.get(srv.url + "/openapi.json").json() == DOCUMENT
    yield srv
    srv.stop()
    output = srv.output()
    assert "Traceback" not in output and "unhandled error" not in output, output


@pytest.fixture(scope="module")
def frame(gardens_point: Path) -> bytes:
    """A real camera frame (a night image of the indexed stretch, a 160 x 120 JPEG: small, as
    a failure report prints the request)."""
    path = sorted((gardens_point / "night_right").iterdir())[5]
    image = cv2.resize(cv2.imread(str(path)), (160, 120), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 70])
    assert ok
    return buf.tobytes()


def _follow_the_rules_in_words(case: schemathesis.Case, frame: bytes) -> schemathesis.Case:
    """A valid (positive) request made to follow the rules the document states in words only
    (JSON Schema cannot say them), so that the server must answer it, and its answer is
    checked against the document: the image is a real frame (random bytes never decode); a
    field comes from the query or the form (the vehicle's id: the header or the form), not
    both; lat, lon and radius_m come together; track (a token the server signs) is left out;
    timestamp only with a vehicle_id, and not in a batch. A copy: the generated case may be
    run again (its metadata, positive or negative, is its own)."""
    if case.meta is None or case.meta.generation.mode is not GenerationMode.POSITIVE:
        return case
    if not case.operation.path.startswith("/v1/localize"):
        return case
    query = dict(case.query or {})
    body: Any = frame
    if case.media_type == "multipart/form-data" and isinstance(case.body, dict):
        body = dict(case.body)
        if "image" in body:
            body["image"] = frame
        if isinstance(body.get("images"), list):
            body["images"] = [frame] * len(body["images"])
        for name in set(body) & set(query):
            del body[name]
    form = body if isinstance(body, dict) else {}
    headers = dict(case.headers or {})
    headers.pop("X-Track", None)
    if "X-Vehicle-Id" in headers:
        form.pop("vehicle_id", None)  # from the header or the form, not both
    given = set(query) | set(form) | ({"vehicle_id"} if "X-Vehicle-Id" in headers else set())
    drop = {"track"}
    if {"lat", "lon", "radius_m"} & given and not {"lat", "lon", "radius_m"} <= given:
        drop |= {"lat", "lon", "radius_m"}
    if "vehicle_id" not in given or case.operation.path.endswith("/batch"):
        drop.add("timestamp")
    for name in drop:
        query.pop(name, None)
        form.pop(name, None)
    return schemathesis.Case(
        case.operation,
        case.method,
        case.path,
        path_parameters=dict(case.path_parameters),
        headers=headers,
        cookies=dict(case.cookies),
        query=query,
        body=body,
        media_type=case.media_type,
        multipart_content_types=case.multipart_content_types,
        meta=copy.deepcopy(case.meta),
    )


@schema.parametrize()
# Under pytest 9 the cases of schema.parametrize() share one test id (the function's name)
# unless the test has a parametrized argument too; pytest-xdist (make test) needs the ids
# unique. `role`: the role of the key the requests carry (admin_key's; every operation takes it).
@pytest.mark.parametrize("role", ["admin"])
def test_the_server_keeps_to_its_document(
    case: schemathesis.Case, server: Server, admin_key, frame: bytes, role: str
) -> None:
    case = _follow_the_rules_in_words(case, frame)
    response = case.call_and_validate(base_url=server.url, headers={"X-API-Key": admin_key[1]})
    SENT[case.operation.label, response.status_code] += 1


def test_fuzzing_ran(server: Server) -> None:
    """The run above sent requests to every operation and met answers (localisations among
    them) and refusals (a summary with -rA). Run it with the test above, not on its own."""
    for (label, status), n in sorted(SENT.items()):
        print(f"{label}: {status} x {n}")
    print(f"total: {SENT.total()} requests")
    statuses = {status for _, status in SENT}
    ops = {label for label, _ in SENT}
    assert {200, 401, 422} <= statuses and len(ops) == len(DOCUMENT_OPERATIONS), SENT
    for route in ("POST /v1/localize", "POST /v1/localize/batch"):
        assert SENT[route, 200] > 0, f"{route}: no request answered: {SENT}"
