"""End to end: a real ``hmpf-serve`` (uvicorn) process on a free loopback port, a real index
built from Gardens Point, real night images posted with httpx (and :class:`hmpf.client.Client`).

* night_right queries match their day_right places;
* an over-limit upload streamed without Content-Length is refused before it has been sent;
* ``/v1/index/reload`` to a new version while clients keep querying: zero failures;
* more concurrent requests than workers + queue: 503 + Retry-After, no crash;
* Ctrl-C (SIGINT) stops the server with one line and exit code 130, no traceback;
* the access log never holds a vehicle's track token or id.
"""

from __future__ import annotations

import signal
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from hmpf.client import Client
from indexer.build import remove
from service.auth import add_key
from tests.service_helpers import BUILD_OPTIONS, Server, build_gp_index

N_REFS = 40


@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_gp_index(gardens_point, tmp_path_factory.mktemp("e2e"), N_REFS)


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("e2e-keys") / "keys.yaml"
    return {
        "file": str(path),
        "vehicle": add_key(path, "car", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


@pytest.fixture(scope="module")
def server(index: Path, keys: dict[str, str], tmp_path_factory) -> Iterator[Server]:
    log = tmp_path_factory.mktemp("e2e-log") / "serve.log"
    srv = Server(
        index, log, keys_file=keys["file"], workers="2", queue="32", max_upload_bytes="1048576"
    )
    yield srv
    srv.stop()
    assert "Traceback" not in srv.output()


def _night(gardens_point: Path, i: int) -> Path:
    return sorted((gardens_point / "night_right").iterdir())[i]


def _post(client: httpx.Client, path: Path, key: str) -> httpx.Response:
    return client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        headers={"X-API-Key": key},
        timeout=60,
    )


def test_night_images_match_their_places(server, keys, gardens_point) -> None:
    picks = list(range(2, N_REFS - 2, 3))  # 12 queries inside the reference stretch
    hits = 0
    with Client(server.url, keys["vehicle"], timeout=60, retries=0) as client:  # hmpf.client
        for i in picks:
            answer = client.localize(_night(gardens_point, i))  # raises unless a 200
            assert answer.index_version == "v0001"
            assert [t.methods for t in answer.tiers] == [["gem", "gist"], ["gem", "gist", "hog"]]
            assert answer.match is not None, answer
            hits += abs(answer.match.reference_id - i) <= 2
    # Measured: all 12 of these night queries land within +-2 frames; allow for 3 misses.
    assert hits >= 9, f"{hits}/{len(picks)} night queries matched"


def test_streamed_upload_is_refused_before_it_is_complete(server, keys) -> None:
    """1 MiB limit; send 2 MiB of chunks without Content-Length and never finish the body:
    the 413 must arrive anyway (the server stopped reading at the limit)."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
        s.sendall(
            b"POST /v1/localize HTTP/1.1\r\nHost: x\r\nContent-Type: image/jpeg\r\n"
            + f"X-API-Key: {keys['vehicle']}\r\n".encode()
            + b"Transfer-Encoding: chunked\r\n\r\n"
        )
        chunk = b"%x\r\n" % 65536 + bytes(65536) + b"\r\n"
        try:
            for _ in range(32):  # 2 MiB, no terminating chunk
                s.sendall(chunk)
        except OSError:
            pass  # the server may close the connection while we still write
        reply = b""
        while b"\r\n\r\n" not in reply:
            part = s.recv(65536)
            if not part:
                break
            reply += part
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]


def test_the_access_log_never_holds_a_track_token_or_a_vehicle_id(
    server, keys, gardens_point
) -> None:
    """The client sends a vehicle's id and track token in headers; a client that puts them
    in the URL anyway is refused (422) and its log line has them blanked."""
    vehicle = "car-secret-417"
    with Client(server.url, keys["vehicle"], timeout=60, retries=0) as client:
        for i in (10, 11, 12):
            answer = client.localize(_night(gardens_point, i), vehicle_id=vehicle)
            assert answer.sequence is not None and answer.vehicle_id == vehicle
        token = client.tracks[vehicle]
    with httpx.Client(base_url=server.url, timeout=60) as c:
        path = _night(gardens_point, 13)
        r = c.post(
            "/v1/localize",
            params={"vehicle_id": vehicle, "track": token},
            content=path.read_bytes(),
            headers={"X-API-Key": keys["vehicle"], "Content-Type": "image/jpeg"},
        )
        assert r.status_code == 422, r.text
        assert "X-Vehicle-Id header" in r.json()["error"]["message"]
        r = c.post(  # the same frame with the headers: served
            "/v1/localize",
            content=path.read_bytes(),
            headers={
                "X-API-Key": keys["vehicle"],
                "Content-Type": "image/jpeg",
                "X-Vehicle-Id": vehicle,
                "X-Track": token,
            },
        )
        assert r.status_code == 200, r.text
        assert r.json()["sequence"]["frames"] == 4
    time.sleep(0.5)  # the log lines of the last requests
    log = server.log.read_text(errors="replace")
    assert "POST /v1/localize" in log  # the access log is on: its lines are checked
    assert "REDACTED" in log
    assert token[:24] not in log
    assert vehicle not in log


def test_reload_while_clients_query_has_zero_failures(server, index, keys, gardens_point) -> None:
    stop = threading.Event()
    statuses: Counter[int] = Counter()
    versions: Counter[str] = Counter()
    lock = threading.Lock()

    def client_loop(seed: int) -> None:
        with httpx.Client(base_url=server.url) as client:
            k = seed
            while not stop.is_set():
                r = _post(client, _night(gardens_point, 3 + k % 30), keys["vehicle"])
                with lock:
                    statuses[r.status_code] += 1
                    if r.status_code == 200:
                        versions[r.json()["index_version"]] += 1
                k += 4

    with ThreadPoolExecutor(4) as pool:
        futures = [pool.submit(client_loop, s) for s in range(4)]
        time.sleep(1.0)
        remove(index, ["Image000.jpg"], options=BUILD_OPTIONS)  # publishes v0002 while queries run
        with httpx.Client(base_url=server.url) as admin:
            r = admin.post("/v1/index/reload", headers={"X-API-Key": keys["admin"]}, timeout=120)
        assert r.status_code == 200, r.text
        assert r.json()["changed"] is True and r.json()["version"] == "v0002"
        time.sleep(2.0)
        stop.set()
        for f in futures:
            f.result()
    assert set(statuses) == {200}, statuses
    assert versions["v0001"] > 0 and versions["v0002"] > 0, versions
    ready = httpx.get(server.url + "/readyz").json()
    assert ready["index_version"] == "v0002"


def test_overload_gets_503_not_a_crash(index, tmp_path, gardens_point) -> None:
    srv = Server(index, tmp_path / "serve.log", auth="false", workers="1", queue="1")
    try:
        data = _night(gardens_point, 10).read_bytes()

        def one(_: int) -> httpx.Response:
            return httpx.post(
                srv.url + "/v1/localize",
                content=data,
                headers={"Content-Type": "image/jpeg"},
                timeout=60,
            )

        with ThreadPoolExecutor(12) as pool:
            replies = list(pool.map(one, range(12)))
        codes = Counter(r.status_code for r in replies)
        assert set(codes) <= {200, 503} and codes[503] > 0 and codes[200] > 0, codes
        for r in replies:
            if r.status_code == 503:
                assert r.headers["retry-after"] == "1"
                assert r.json()["error"]["code"] == "overloaded"
        # still serving afterwards
        assert httpx.get(srv.url + "/healthz").status_code == 200
        assert one(0).status_code == 200
    finally:
        srv.stop()
    assert "Traceback" not in srv.output()
    assert "authentication is OFF" in srv.output()


def test_ctrl_c_exits_130_with_one_line(index, tmp_path) -> None:
    srv = Server(index, tmp_path / "serve.log", auth="false", workers="1")
    try:
        srv.proc.send_signal(signal.SIGINT)
        rc = srv.proc.wait(60)
    finally:
        srv.stop()
    out = srv.output()
    assert rc == 130, out
    assert "Traceback" not in out and out.count("hmpf-serve: interrupted") == 1, out
