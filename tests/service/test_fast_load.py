"""Fast, safe loads through a real uvicorn server on loopback, in a thread of the test
process, with the real engine over real (small, synthetic) indexes.

* A version with a matching verification stamp opens without hashing and answers at once;
  its full check runs in the background and passes.
* A forged stamp over a corrupted file (the stamp rewritten from the damaged file's stat) is
  caught by that check: queries get a JSON 503 ``index_corrupt`` (never a 500), ``/readyz``
  says not ready, the metric counts it and the stamp is gone.
* The same after a reload: the previous, sound version answers again.
* Reloads while clients query: no request fails.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import pytest
import uvicorn

from hmpf.config import parse_config
from hmpf.index import layout
from indexer import maintenance
from indexer.build import BuildOptions, build, remove
from service.app import create_app
from service.engine import Engine
from service.server import uvicorn_config
from service.settings import load_settings
from tests.conftest import SERVICE_CONFIG, synthetic_image, write_synthetic_images
from tests.service_helpers import metric_sum

OPTS = BuildOptions(workers=1, progress=False)


class Records(logging.Handler):
    """The messages of the ``hmpf`` loggers while attached."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


class RealServer:
    """uvicorn serving ``create_app`` (its own engine over ``index``) in a thread."""

    def __init__(self, index: Path, **overrides: Any) -> None:
        settings = load_settings(None, index=index, auth=False, port=0, **overrides)
        self.app = create_app(settings)
        self.engine: Engine = self.app.state.engine
        self.server = uvicorn.Server(uvicorn_config(self.app, settings))
        self.thread = threading.Thread(target=lambda: asyncio.run(self.server.serve()))
        self.log = Records()

    def __enter__(self) -> RealServer:
        logging.getLogger("hmpf").addHandler(self.log)
        self.thread.start()
        deadline = time.monotonic() + 120
        while not self.server.started:
            assert self.thread.is_alive() and time.monotonic() < deadline, "server did not start"
            time.sleep(0.02)
        (sock,) = self.server.servers[0].sockets
        self.url = f"http://127.0.0.1:{sock.getsockname()[1]}"
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(30)
        logging.getLogger("hmpf").removeHandler(self.log)

    def get(self, path: str) -> httpx.Response:
        return httpx.get(self.url + path, timeout=30)

    def localize(self, client: httpx.Client | None = None) -> httpx.Response:
        post = client.post if client is not None else httpx.post
        return post(
            self.url + "/v1/localize",
            content=PNG,
            headers={"Content-Type": "image/png"},
            timeout=60,
        )

    def metric(self, name: str, **labels: str) -> float:
        """The sum of ``name``'s samples whose labels include ``labels``."""
        return metric_sum(self.get("/metrics").text, name, **labels)


PNG = cv2.imencode(".png", cv2.cvtColor(synthetic_image(2), cv2.COLOR_RGB2BGR))[1].tobytes()


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """v0001 over 6 synthetic references, v0002 without the last; CURRENT names v0001."""
    base = tmp_path_factory.mktemp("fast-load")
    refs = write_synthetic_images(base / "refs", 6)
    root = base / "index"
    build(parse_config(SERVICE_CONFIG), refs, root, options=OPTS)
    remove(root, ["img005.png"], options=OPTS)
    layout.set_current(root, "v0001")
    return root


@pytest.fixture
def index(built: Path, tmp_path: Path) -> Iterator[Path]:
    """A copy of :func:`built`, stamped by ``hmpf-index verify`` (a copy is other files: the
    stamps it copied do not match it)."""
    root = tmp_path / "index"
    shutil.copytree(built, root)
    assert maintenance.verify_all(root) == {"v0001": [], "v0002": []}
    yield root


def _largest(version: Path) -> Path:
    listed = layout.read_manifest(version)["files"]
    return version / max(listed, key=lambda rel: listed[rel]["bytes"])


def _corrupt_and_forge_the_stamp(version: Path) -> Path:
    """Change one byte of the largest file (same size), then stamp the damaged file as if it
    had passed a full check: only hashing can find it now."""
    data = _largest(version)
    raw = bytearray(data.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    data.write_bytes(bytes(raw))
    manifest = layout.read_manifest(version)
    assert layout.write_stamp(version, manifest)
    assert layout.stamp_matches(version, manifest)
    return data


def test_a_stamped_version_answers_at_once_and_passes_its_background_check(index: Path) -> None:
    with RealServer(index, workers=1) as s:
        reader = s.engine.current.reader
        assert (reader.verified_by, reader.verify_seconds) == ("stamp", None)  # nothing hashed
        assert s.localize().status_code == 200
        assert s.engine.check_done(timeout=60)
        info = s.get("/v1/index").json()
        assert info["version"] == "v0001"
        assert info["verification"]["state"] == "passed"
        assert info["verification"]["check_seconds"] is not None
        assert info["verification"]["problems"] == []
        assert s.metric("hmpf_index_verification", state="passed") == 1
        assert s.metric("hmpf_index_verification", state="corrupt") == 0
        assert s.metric("hmpf_index_corrupt_total") == 0
        assert s.get("/readyz").status_code == 200


def test_a_forged_stamp_over_a_corrupt_file_is_caught_by_the_background_check(
    index: Path,
) -> None:
    data = _corrupt_and_forge_the_stamp(index / "v0001")
    with RealServer(index, workers=1) as s:
        assert s.engine.current.reader.verified_by == "stamp"  # the forgery got it opened
        assert s.engine.check_done(timeout=60)
        r = s.localize()
        assert r.status_code == 503, r.text
        assert r.headers["content-type"] == "application/json"
        error = r.json()["error"]
        assert error["code"] == "index_corrupt"
        assert "v0001 is corrupt" in error["message"] and "hmpf-index verify" in error["message"]
        assert str(index) not in r.text  # no server path in an answer
        batch = httpx.post(
            s.url + "/v1/localize/batch",
            files=[("images", ("a.png", PNG, "image/png"))],
            timeout=60,
        )
        assert batch.status_code == 503 and batch.json()["error"]["code"] == "index_corrupt"
        assert s.get("/v1/references").status_code == 503
        ready = s.get("/readyz")
        assert ready.status_code == 503 and ready.json()["error"]["code"] == "index_corrupt"
        assert s.get("/healthz").status_code == 200  # alive: a restart would not mend the file
        info = s.get("/v1/index").json()
        assert info["verification"]["state"] == "corrupt"
        (problem,) = info["verification"]["problems"]
        assert problem.startswith(f"{data.name}: sha256 differs") and str(index) not in problem
        assert s.metric("hmpf_index_corrupt_total") == 1
        assert s.metric("hmpf_index_verification", state="corrupt") == 1
        assert s.metric("hmpf_index_verification", state="checking") == 0
        assert s.metric("hmpf_requests_total", status="500") == 0
        assert s.metric("hmpf_requests_total", route="/v1/localize", status="503") == 1
        assert any("INDEX VERSION v0001 IS CORRUPT" in m for m in s.log.messages)
    assert not layout.stamp_path(index / "v0001").exists()  # the next load hashes it all


def test_a_reload_whose_check_fails_hands_back_to_the_previous_version(index: Path) -> None:
    _corrupt_and_forge_the_stamp(index / "v0002")
    with RealServer(index, workers=1) as s:
        assert s.engine.check_done(timeout=60)
        assert s.get("/v1/index").json()["verification"]["state"] == "passed"
        layout.set_current(index, "v0002")  # as a careless writer would: unverified
        r = httpx.post(s.url + "/v1/index/reload", timeout=60)
        assert r.status_code == 200 and r.json()["version"] == "v0002", r.text
        assert s.engine.check_done(timeout=60)
        info = s.get("/v1/index").json()
        assert (info["version"], info["current"]) == ("v0001", "v0002")
        assert info["verification"]["state"] == "passed"
        answer = s.localize()
        assert answer.status_code == 200 and answer.json()["index_version"] == "v0001"
        assert s.get("/readyz").status_code == 200
        assert s.metric("hmpf_index_corrupt_total") == 1
        assert s.metric("hmpf_index_behind") == 1
        assert s.metric("hmpf_index_info", version="v0001") == 1
        assert s.metric("hmpf_index_info", version="v0002") == 0
        assert any("Version v0001 answers again" in m for m in s.log.messages)
    assert not layout.stamp_path(index / "v0002").exists()


def test_reloads_while_clients_query_fail_no_request(index: Path) -> None:
    """Three clients query without pause over loopback while the version is switched six
    times (``hmpf-index use``, then ``POST /v1/index/reload``): every answer is a 200."""
    statuses: Counter[int] = Counter()
    versions: Counter[str] = Counter()
    failures: list[str] = []
    stop = threading.Event()
    with RealServer(index, workers=2, queue=8) as s:

        def client() -> None:
            with httpx.Client() as c:
                while not stop.is_set():
                    try:
                        r = s.localize(c)
                    except httpx.HTTPError as exc:
                        failures.append(repr(exc))
                        continue
                    statuses[r.status_code] += 1
                    if r.status_code == 200:
                        versions[r.json()["index_version"]] += 1
                    else:
                        failures.append(r.text[:300])

        threads = [threading.Thread(target=client) for _ in range(3)]
        for t in threads:
            t.start()
        try:
            for i in range(6):
                target = ("v0002", "v0001")[i % 2]
                maintenance.use(index, target)  # verified in full, stamped
                r = httpx.post(s.url + "/v1/index/reload", timeout=60)
                assert r.status_code == 200 and r.json()["version"] == target, r.text
                seen = versions[target]
                deadline = time.monotonic() + 30
                while versions[target] < seen + 3 and time.monotonic() < deadline:
                    time.sleep(0.02)
                assert s.engine.current.verification in ("checking", "passed")
        finally:
            stop.set()
            for t in threads:
                t.join(60)
        assert not failures, failures[:3]
        assert set(statuses) == {200} and versions["v0001"] > 0 and versions["v0002"] > 0
        assert s.metric("hmpf_index_reloads_total", trigger="request") == 6
        assert s.metric("hmpf_index_corrupt_total") == 0


def test_a_file_truncated_while_serving_is_a_503_not_a_500(index: Path) -> None:
    """A file damaged after its check passed (here: the rows the final tier reads from disk
    cut off) is found by the query that needs them: a JSON 503 ``index_corrupt`` without
    a server path, never a 500 blaming the image."""
    import h5py

    with RealServer(index, workers=1) as s:
        assert s.localize().status_code == 200
        assert s.engine.check_done(timeout=60)
        reader = s.engine.current.reader
        assert reader.on_demand("sad")  # a method of the later tier only: read from disk
        path = reader.path / layout.REFERENCES_H5
        with h5py.File(path, "r") as f:
            cut = f["global"]["sad"].id.get_offset()
        with open(path, "r+b") as fh:
            fh.truncate(cut)
        r = s.localize()
        assert r.status_code == 503, r.text
        assert r.headers["content-type"] == "application/json"
        error = r.json()["error"]
        assert error["code"] == "index_corrupt" and "hmpf-index verify" in error["message"]
        assert str(index) not in r.text
        assert s.metric("hmpf_requests_total", status="500") == 0
        assert any("short read" in m for m in s.log.messages)
