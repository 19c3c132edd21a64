"""``hmpf.client`` against a real ``hmpf-serve`` (uvicorn, loopback) on a real index
(:func:`conftest.service_index`: 20 Gardens Point day_right references with positions), with
real night frames; no mocks.

* answers are the service's models, equal to what a hand-written HTTP call gets;
* a 4xx raises at once with the service's error body and is sent once (the server's
  request counter says so);
* sequence mode: the track token is carried across one vehicle's frames, kept apart per
  vehicle, taken from a batch, and dropped when the service refuses it;
* the docs' vehicle example (docs/client.md) runs as written.

The real server cannot answer 503 or refuse connections on demand, so those retries are tested
against a tiny ``http.server`` on 127.0.0.1 that answers a script (503s with Retry-After, then
a real answer recorded from the real server) or closes every connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import pickle
import re
import socket
import threading
import time
from collections.abc import Iterator
from email.utils import formatdate
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from hmpf.client import (
    AsyncClient,
    Client,
    ServiceError,
    ServiceUnreachable,
    UnexpectedAnswer,
    encode_image,
)
from hmpf.imageio import load_image
from service.auth import add_key
from service.schemas import BatchResponse, IndexInfo, LocalizeResponse
from tests.service_helpers import ROOT, Server, free_port


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("client-keys") / "keys.yaml"
    return {"file": str(path), "vehicle": add_key(path, "car", "vehicle")}


@pytest.fixture(scope="module")
def server(
    service_index: Path, keys: dict[str, str], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Server]:
    log = tmp_path_factory.mktemp("client-log") / "serve.log"
    srv = Server(service_index, log, keys_file=keys["file"], workers="1", queue="8")
    yield srv
    srv.stop()
    assert "Traceback" not in srv.output()


@pytest.fixture(scope="module")
def night(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "night_right").iterdir())


@pytest.fixture
def client(server: Server, keys: dict[str, str]) -> Iterator[Client]:
    with Client(server.url, keys["vehicle"], timeout=30, retries=3, backoff=0.01) as c:
        yield c


def _requests(server: Server, route: str, status: int) -> float:
    """``hmpf_requests_total`` of ``route`` answered ``status`` (the server's own count)."""
    text = httpx.get(server.url + "/metrics").text
    total = 0.0
    for labels, value in re.findall(r"^hmpf_requests_total\{(.*)\} (\S+)$", text, re.MULTILINE):
        found = dict(re.findall(r'(\w+)="([^"]*)"', labels))
        if found["route"] == route and found["status"] == str(status):
            total += float(value)
    return total


def _without_timing(answer: LocalizeResponse) -> dict[str, Any]:
    body = answer.model_dump()
    body.pop("timing_ms")
    for tier in body["tiers"]:
        tier.pop("time_ms")
    return body


# -- answers ---------------------------------------------------------------------------------------
def test_localize_returns_the_services_model_as_raw_http_gets_it(
    client: Client, server: Server, keys: dict[str, str], night: list[Path]
) -> None:
    path = night[6]
    answer = client.localize(path, top_k=3, lat=-27.4770, lon=153.0280, radius_m=5000)
    raw = httpx.post(
        server.url + "/v1/localize",
        params={"top_k": 3, "lat": -27.4770, "lon": 153.0280, "radius_m": 5000},
        content=path.read_bytes(),
        headers={"X-API-Key": keys["vehicle"], "Content-Type": "image/jpeg"},
        timeout=30,
    )
    assert raw.status_code == 200, raw.text
    assert isinstance(answer, LocalizeResponse)
    assert _without_timing(answer) == _without_timing(LocalizeResponse.model_validate(raw.json()))
    assert len(answer.candidates) == 3 and answer.prior is not None and answer.prior.applied
    assert answer.match is not None and 0 <= answer.match.reference_id < 20
    assert answer.sequence is None and answer.vehicle_id is None
    # the same frame as bytes, and as a decoded RGB array sent losslessly: the same place
    assert (
        client.localize(path.read_bytes(), top_k=3).candidates
        == client.localize(str(path), top_k=3).candidates
    )
    with Client(server.url, keys["vehicle"], array_format="png") as png:
        from_array = png.localize(load_image(path), top_k=3)
    assert from_array.match is not None and from_array.match.reference_id == (
        answer.match.reference_id
    )


def test_index_is_the_services_index_info(client: Client, server: Server, keys) -> None:
    info = client.index()
    raw = httpx.get(server.url + "/v1/index", headers={"X-API-Key": keys["vehicle"]})
    assert isinstance(info, IndexInfo) and info == IndexInfo.model_validate(raw.json())
    assert info.references == 20 and info.version == "v0001" and info.has_positions
    assert info.root is None  # a vehicle key is not shown the server's folder


def test_batch_answers_in_order_with_a_bad_image_as_its_own_error(
    client: Client, night: list[Path]
) -> None:
    batch = client.localize_batch([night[4], b"not an image", night[12]], top_k=2)
    assert isinstance(batch, BatchResponse) and [r.index for r in batch.results] == [0, 1, 2]
    first, bad, last = batch.results
    assert bad.result is None and bad.error is not None, bad
    assert first.result is not None and last.result is not None and batch.track is None
    for item, frame in ((first, night[4]), (last, night[12])):
        alone = client.localize(frame, top_k=2)
        assert item.result is not None and item.result.candidates == alone.candidates


def test_async_client_answers_as_the_sync_one(client: Client, server, keys, night) -> None:
    async def drive() -> tuple[LocalizeResponse, LocalizeResponse, IndexInfo]:
        async with AsyncClient(server.url, keys["vehicle"], backoff=0.01) as c:
            one = await c.localize(night[8], top_k=2)
            seq = await c.localize(night[8], vehicle_id="async-car")
            seq = await c.localize(night[9], vehicle_id="async-car")
            return one, seq, await c.index()

    one, seq, info = asyncio.run(drive())
    assert _without_timing(one) == _without_timing(client.localize(night[8], top_k=2))
    assert seq.sequence is not None and seq.sequence.status == "tracking"
    assert info == client.index()


# -- errors: never retried -----------------------------------------------------------------------
def test_a_4xx_raises_at_once_with_the_body_and_is_sent_once(
    server: Server, keys: dict[str, str], night: list[Path]
) -> None:
    route = "/v1/localize"
    before = {s: _requests(server, route, s) for s in (401, 415, 422)}
    with Client(server.url, "wrong-key", retries=5, backoff=0.5) as c:
        t = time.monotonic()
        with pytest.raises(ServiceError) as exc:
            c.localize(night[3])
        assert time.monotonic() - t < 5  # no backoff waits
    assert exc.value.status == 401 and exc.value.code == "unauthorized"
    assert exc.value.body == {"error": {"code": "unauthorized", "message": exc.value.message}}
    assert "X-API-Key" in exc.value.message and str(exc.value).startswith("401 unauthorized")
    copy = pickle.loads(pickle.dumps(exc.value))  # e.g. out of a worker process
    assert (copy.status, copy.body, str(copy)) == (401, exc.value.body, str(exc.value))
    with Client(server.url, keys["vehicle"], retries=5, backoff=0.5) as c:
        with pytest.raises(ServiceError) as bad_image:
            c.localize(b"GIF89a this is not a frame")
        with pytest.raises(ServiceError) as bad_prior:
            c.localize(night[3], lat=-27.47)  # a GPS prior needs lon and radius_m too
    assert bad_image.value.status == 415 and bad_image.value.code == "unsupported_media_type"
    assert bad_prior.value.status == 422 and bad_prior.value.code == "invalid_request"
    assert "lat, lon and radius_m" in bad_prior.value.message
    after = {s: _requests(server, route, s) for s in (401, 415, 422)}
    assert {s: after[s] - before[s] for s in after} == {401: 1, 415: 1, 422: 1}


def test_bad_arguments_are_refused_before_sending(tmp_path: Path) -> None:
    with Client(f"http://127.0.0.1:{free_port()}", retries=0) as c:  # nothing listens there
        with pytest.raises(TypeError, match="uint8"):
            c.localize(np.zeros((8, 8, 3), np.float32))
        with pytest.raises(ValueError, match=r"H x W x 3"):
            c.localize(np.zeros((8, 8, 4), np.uint8))
        with pytest.raises(ValueError, match="empty"):
            c.localize(b"")
        with pytest.raises(FileNotFoundError):
            c.localize(tmp_path / "missing.jpg")
        with pytest.raises(TypeError, match="path, bytes or a numpy array"):
            c.localize(12)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="at least one image"):
            c.localize_batch([])
        with pytest.raises(TypeError, match="unexpected keyword argument 'radius'"):
            c.localize(b"\xff\xd8\xff", radius=5)  # type: ignore[call-arg]
        with pytest.raises(TypeError, match="argument 'timestamp'"):  # a batch has none
            c.localize_batch([b"\xff\xd8\xff"], timestamp=1.0)  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="http://"):
        Client("127.0.0.1:8000")
    grey, content_type = encode_image(np.full((16, 16), 128, np.uint8))
    assert content_type == "image/jpeg" and grey.startswith(b"\xff\xd8\xff")


# -- retries: a scripted stub on loopback --------------------------------------------------------
class Stub:
    """An ``http.server`` on 127.0.0.1 answering each request with the next of ``script``
    (status, headers, body; the last one repeats), request ``n`` (1: the first) after
    ``pause[n]`` seconds; it notes when each request came."""

    def __init__(
        self, script: list[tuple[int, dict[str, str], bytes]], pause: dict[int, float] | None = None
    ) -> None:
        self.script, self.times, self.pause = script, [], pause or {}
        stub = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                stub.times.append(time.monotonic())
                n = len(stub.times)
                time.sleep(stub.pause.get(n, 0.0))
                status, headers, body = stub.script[min(n, len(stub.script)) - 1]
                with contextlib.suppress(OSError):  # a client that timed out has gone
                    self.send_response(status)
                    for k, v in {**headers, "Content-Length": str(len(body))}.items():
                        self.send_header(k, v)
                    self.end_headers()
                    self.wfile.write(body)

            def log_message(self, *args: Any) -> None:
                pass

        self.http = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.http.server_address[1]}"
        threading.Thread(target=self.http.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.http.shutdown()
        self.http.server_close()


@pytest.fixture(scope="module")
def recorded(server: Server, keys: dict[str, str], night: list[Path]) -> bytes:
    """A real answer of the real server, as bytes."""
    r = httpx.post(
        server.url + "/v1/localize",
        content=night[5].read_bytes(),
        headers={"X-API-Key": keys["vehicle"], "Content-Type": "image/jpeg"},
        timeout=30,
    )
    assert r.status_code == 200, r.text
    return r.content


BUSY = b'{"error": {"code": "overloaded", "message": "all workers are busy"}}'


def test_503_is_retried_after_retry_after_then_answered(recorded: bytes, night) -> None:
    stub = Stub([(503, {"Retry-After": "1"}, BUSY), (200, {}, recorded)])
    try:
        with Client(stub.url, "k", retries=2, backoff=0.0, jitter=False) as c:
            answer = c.localize(night[5])
    finally:
        stub.close()
    assert answer == LocalizeResponse.model_validate_json(recorded)
    assert len(stub.times) == 2
    assert stub.times[1] - stub.times[0] >= 0.95  # Retry-After: 1, not the backoff's 0 s


def test_503_retries_are_bounded_and_end_in_the_services_error(night) -> None:
    # The HTTP-date form of Retry-After, whole seconds: 3 s ahead stays over max_backoff
    # (0.3 s) after the truncation and a slow first request (+1 s was in the past once).
    later = formatdate(time.time() + 3, usegmt=True)
    stub = Stub([(503, {"Retry-After": later}, BUSY), (503, {"Retry-After": "0"}, BUSY)])
    try:
        with Client(stub.url, "k", retries=2, backoff=5.0, max_backoff=0.3) as c:
            t = time.monotonic()
            with pytest.raises(ServiceError) as exc:
                c.localize(night[5])
            elapsed = time.monotonic() - t
    finally:
        stub.close()
    assert len(stub.times) == 3  # the first try and 2 retries
    assert exc.value.status == 503 and exc.value.code == "overloaded"
    assert exc.value.retry_after == 0.0
    # the date's wait capped by max_backoff (0.3 s), then Retry-After: 0
    assert 0.15 <= stub.times[1] - stub.times[0] < 0.6 and elapsed < 2


def test_a_timeout_is_retried_and_then_the_error(recorded: bytes, night) -> None:
    stub = Stub([(200, {}, recorded)], pause={1: 1.5, 3: 1.5})  # 1st and 3rd: too slow
    try:
        with Client(stub.url, timeout=0.3, retries=1, backoff=0.0) as c:
            answer = c.localize(night[5])  # the 1st times out, the 2nd answers
            assert answer == LocalizeResponse.model_validate_json(recorded)
        with Client(stub.url, timeout=0.3, retries=0) as c:
            with pytest.raises(ServiceUnreachable, match=r"after 1 try: ReadTimeout"):
                c.localize(night[5])
    finally:
        stub.close()
    assert len(stub.times) == 3


def test_a_success_body_that_is_not_the_model_is_an_error(night) -> None:
    stub = Stub([(200, {"Content-Type": "application/json"}, b'{"hello": "world"}')])
    try:
        with Client(stub.url) as c, pytest.raises(UnexpectedAnswer, match="LocalizeResponse"):
            c.localize(night[5])
    finally:
        stub.close()
    assert len(stub.times) == 1


def test_connection_refused_is_retried_then_raises() -> None:
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    with Client(url, "k", retries=2, backoff=0.1, jitter=False) as c:
        t = time.monotonic()
        with pytest.raises(ServiceUnreachable, match=r"after 3 tries: ConnectError") as exc:
            c.localize(b"\xff\xd8\xff fake jpeg")
        elapsed = time.monotonic() - t
    assert url in str(exc.value) and isinstance(exc.value.__cause__, httpx.ConnectError)
    assert elapsed >= 0.3  # waits 0.1 s, then 0.2 s


def test_dropped_connections_are_retried_a_bounded_number_of_times() -> None:
    """A listener that accepts and closes every connection: each try is one connection."""
    accepted: list[float] = []
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(0.2)
        port = listener.getsockname()[1]
        stop = threading.Event()

        def serve() -> None:
            while not stop.is_set():
                with contextlib.suppress(TimeoutError):
                    conn, _ = listener.accept()
                    accepted.append(time.monotonic())
                    conn.close()

        thread = threading.Thread(target=serve)
        thread.start()
        try:
            with Client(f"http://127.0.0.1:{port}", retries=3, backoff=0.01) as c:
                with pytest.raises(ServiceUnreachable, match="after 4 tries"):
                    c.index()
        finally:
            stop.set()
            thread.join()
    assert len(accepted) == 4


# -- sequence mode ---------------------------------------------------------------------------------
def test_the_track_is_carried_per_vehicle(client: Client, night: list[Path]) -> None:
    statuses: dict[str, list[tuple[str, int]]] = {"car-a": [], "car-b": []}
    for i in range(3):  # two vehicles, interleaved: each must get its own token back
        for vid, offset in (("car-a", 5), ("car-b", 12)):
            answer = client.localize(night[offset + i], vehicle_id=vid, timestamp=float(i))
            seq = answer.sequence
            assert seq is not None and answer.vehicle_id == vid
            statuses[vid].append((seq.status, seq.frames))
            assert client.tracks[vid] == seq.track
    expected = [("started", 1), ("tracking", 2), ("tracking", 3)]
    assert statuses == {"car-a": expected, "car-b": expected}
    assert client.tracks["car-a"] != client.tracks["car-b"]
    # an explicit track= overrides the kept one (here: car-b's, refused for car-a)
    with pytest.raises(ServiceError) as exc:
        client.localize(night[8], vehicle_id="car-a", track=client.tracks["car-b"])
    assert exc.value.status == 422 and exc.value.code == "invalid_track"
    assert "car-a" not in client.tracks  # dropped: the next frame starts afresh
    answer = client.localize(night[8], vehicle_id="car-a")
    assert answer.sequence is not None and answer.sequence.status == "started"


def test_a_batch_carries_the_track_too(client: Client, night: list[Path]) -> None:
    batch = client.localize_batch(night[6:9], vehicle_id="car-c")
    assert batch.track is not None and client.tracks["car-c"] == batch.track
    frames = [r.result.sequence.frames for r in batch.results if r.result and r.result.sequence]
    assert frames == [1, 2, 3]
    answer = client.localize(night[9], vehicle_id="car-c")
    assert answer.sequence is not None
    assert (answer.sequence.status, answer.sequence.frames) == ("tracking", 4)


# -- the docs -------------------------------------------------------------------------------------
def test_the_docs_vehicle_example_runs(
    server: Server, keys: dict[str, str], night: list[Path], tmp_path: Path, capsys
) -> None:
    text = (ROOT / "docs" / "client.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    assert len(blocks) == 1
    code = blocks[0]
    assert len(code.strip().splitlines()) <= 12  # "a vehicle in ten lines" (and its imports)
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in night[5:9]:
        (frames / p.name).symlink_to(p)
    for placeholder, value in (
        ('"http://127.0.0.1:8000"', repr(server.url)),
        ('"YOUR-VEHICLE-KEY"', repr(keys["vehicle"])),
        ('"frames/*.jpg"', repr(f"{frames}/*.jpg")),
    ):
        assert code.count(placeholder) == 1, placeholder
        code = code.replace(placeholder, value)
    exec(compile(code, "docs/client.md", "exec"), {"__name__": "docs_example"})
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == [f"frame {n}" for n in range(4)], lines
    assert all(re.search(r": at Image\d+\.jpg \(|: not sure yet \(", line) for line in lines)


def test_the_readme_shows_the_docs_vehicle_example() -> None:
    """README's vehicle example is the block the test above runs (docs/client.md)."""
    fence = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)
    (example,) = fence.findall((ROOT / "docs" / "client.md").read_text())
    assert example in fence.findall((ROOT / "README.md").read_text())
