"""Two real ``hmpf-serve`` replicas behind a real HAProxy, on loopback (docs/replicas.md).

The replicas serve one index folder with one keys file and one sequence key file, and watch
the index's ``CURRENT`` (``watch_current_s``); HAProxy's configuration is the one
``hmpf-serve replicas haproxy`` writes (``deploy/haproxy/`` for two replicas).

* load through the balancer spreads over both replicas (each one's ``/metrics``);
* a JSON 4xx reaches one replica once: :class:`hmpf.client.Client` does not retry it;
* a vehicle's consecutive frames answered by different replicas continue one track;
* ``hmpf-index use`` reaches both replicas within seconds, with no failed request meanwhile;
* a version that cannot be loaded keeps the old one in service and every replica says so
  (``/v1/index``'s ``current``, ``hmpf_index_behind``, the failures counter);
* a replica killed (SIGKILL) under load loses no request the client retries.

The watch itself is also tested in process (no HAProxy needed). Without HAProxy the other
tests are skipped, with the reason; with ``HMPF_REQUIRE_HAPROXY=1`` (set
by ``.ci/run``, which installs it: ``make haproxy``) they fail instead. The tests run in this
order and share the servers; the last one kills a replica.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest

from hmpf.client import Client, ServiceError
from hmpf.config import parse_config
from hmpf.errors import ConfigError
from hmpf.index import layout
from indexer.build import build, remove
from indexer.maintenance import use
from service.auth import add_key
from service.cli import main as serve_main
from service.replicas import HaproxyOptions, error_files, haproxy_config, write_haproxy
from service.settings import load_settings
from tests.conftest import SERVICE_CONFIG, copy_gp
from tests.service_helpers import (
    BUILD_OPTIONS,
    ROOT,
    LoggedProcess,
    Server,
    free_port,
    metric_sum,
)

N_REFS = 20
#: How often the replicas look at CURRENT (s), and the longest a switch may take here.
WATCH_S = 0.5
SWITCH_DEADLINE_S = 20.0


def _haproxy() -> str:
    found = shutil.which("haproxy") or shutil.which("haproxy", path="/usr/sbin:/sbin")
    if found is None:
        why = "no haproxy on PATH or in /usr/sbin (make haproxy: apt-get install haproxy)"
        if os.environ.get("HMPF_REQUIRE_HAPROXY") == "1":
            pytest.fail(f"HMPF_REQUIRE_HAPROXY=1 but {why}")
        pytest.skip(why)
    return found


@pytest.fixture(scope="module")
def haproxy_bin() -> str:
    return _haproxy()


# -- no servers -------------------------------------------------------------------------------
def test_shipped_config_is_the_generated_one_and_valid(haproxy_bin: str) -> None:
    shipped = ROOT / "deploy" / "haproxy"
    assert (shipped / "haproxy.cfg").read_text() == haproxy_config(HaproxyOptions())
    for name, text in error_files().items():
        assert (shipped / name).read_bytes() == text.encode(), name
    check = subprocess.run(
        [haproxy_bin, "-c", "-f", str(shipped / "haproxy.cfg")], capture_output=True, text=True
    )
    assert check.returncode == 0, check.stdout + check.stderr
    # what HAProxy answers itself: the service's error JSON; a failed replica is retryable
    assert "HTTP/1.1 503" in error_files()["errors/502.http"]
    assert "Retry-After: 1" in error_files()["errors/503.http"]


def test_serve_replicas_command_writes_the_shipped_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``hmpf-serve replicas haproxy`` with its defaults writes ``deploy/haproxy/``."""
    with pytest.raises(SystemExit) as done:
        serve_main(["replicas", "--help"])
    assert done.value.code == 0
    assert "usage: hmpf-serve replicas" in capsys.readouterr().out
    assert serve_main(["replicas", "haproxy", "--out", str(tmp_path)]) == 0
    shipped = ROOT / "deploy" / "haproxy"
    written = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    assert written == sorted(p.relative_to(shipped) for p in shipped.rglob("*") if p.is_file())
    for name in written:
        assert (tmp_path / name).read_bytes() == (shipped / name).read_bytes(), name
    with pytest.raises(SystemExit) as refused:
        serve_main(["replicas", "run", "--index", str(tmp_path), "--replicas", "0", "--out", "x"])
    assert "at least 1" in str(refused.value.code)


def test_watch_setting_is_validated() -> None:
    assert load_settings(auth=False).watch_current_s == 0  # off unless asked for
    assert load_settings(auth=False, watch_current_s="2").watch_current_s == 2.0
    with pytest.raises(ConfigError, match="watch_current_s"):
        load_settings(auth=False, watch_current_s=-1)
    with pytest.raises(ConfigError, match="watch_current_s"):
        load_settings(auth=False, watch_current_s="often")


def test_watch_follows_current_in_process(service_index: Path, tmp_path: Path) -> None:
    """The watch alone (no HAProxy needed): a version published while the app runs is loaded
    by itself; the metrics say so; an unreadable CURRENT is reported, not acted on."""
    from fastapi.testclient import TestClient

    from service.app import create_app

    index = tmp_path / "index"
    shutil.copytree(service_index, index)
    settings = load_settings(None, index=index, auth=False, workers=1, watch_current_s=0.1)
    with TestClient(create_app(settings)) as c:
        assert c.get("/v1/index").json()["version"] == "v0001"
        assert "hmpf_index_behind 0.0" in c.get("/metrics").text
        remove(index, ["Image000.jpg"], options=BUILD_OPTIONS)  # publishes v0002
        _wait("the watch loads v0002", lambda: c.get("/v1/index").json()["version"] == "v0002")
        text = c.get("/metrics").text
        assert 'hmpf_index_reloads_total{trigger="watch"} 1.0' in text
        assert 'hmpf_index_info{version="v0002"} 1.0' in text and "v0001" not in text
        assert "hmpf_index_behind 0.0" in text
        (index / layout.CURRENT).write_text("not a version\n")
        body = c.get("/v1/index").json()
        assert (body["version"], body["current"]) == ("v0002", None)
        assert "hmpf_index_behind 1.0" in c.get("/metrics").text
        time.sleep(0.5)  # several polls: nothing to load, nothing failed
        text = c.get("/metrics").text
        assert 'hmpf_index_reload_failures_total{trigger="watch"} 0.0' in text
        assert c.get("/readyz").json()["index_version"] == "v0002"
        layout.set_current(index, "v0002")
        assert "hmpf_index_behind 0.0" in c.get("/metrics").text


# -- servers ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """v0001 (20 references) and v0002 (without the first), CURRENT on v0001."""
    base = tmp_path_factory.mktemp("replicas")
    refs = copy_gp(gardens_point, "day_right", base / "refs", N_REFS)
    out = base / "index"
    build(parse_config(SERVICE_CONFIG), refs, out, options=BUILD_OPTIONS)
    remove(out, ["Image000.jpg"], options=BUILD_OPTIONS)
    use(out, "v0001")
    return out


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    base = tmp_path_factory.mktemp("replicas-keys")
    path = base / "keys.yaml"
    sequence = base / "sequence.key"
    sequence.write_text(secrets.token_hex(32) + "\n")
    sequence.chmod(0o600)
    return {
        "file": str(path),
        "sequence_file": str(sequence),
        "vehicle": add_key(path, "car", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


@pytest.fixture(scope="module")
def replicas(
    index: Path, keys: dict[str, str], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[list[Server]]:
    logs = tmp_path_factory.mktemp("replicas-logs")

    def start(i: int) -> Server:
        return Server(
            index,
            logs / f"replica{i}.log",
            keys_file=keys["file"],
            sequence_key_file=keys["sequence_file"],
            workers="1",
            queue="8",
            watch_current_s=str(WATCH_S),
        )

    with ThreadPoolExecutor(2) as pool:
        started = [pool.submit(start, i) for i in (1, 2)]
        servers = [f.result() for f in started]
    yield servers
    for s in servers:
        s.stop()
    assert "Traceback" not in servers[0].output()


class Balancer(LoggedProcess):
    """HAProxy in the foreground with the generated configuration."""

    stop_wait_s = 10.0

    def __init__(self, binary: str, servers: list[Server], folder: Path) -> None:
        port = free_port()
        self.url = f"http://127.0.0.1:{port}"
        options = HaproxyOptions(
            bind=f"127.0.0.1:{port}",
            replicas=tuple(f"127.0.0.1:{s.port}" for s in servers),
            check_interval_s=0.5,
            server_timeout_s=30,
        )
        cfg = write_haproxy(options, folder)
        self.log = folder / "haproxy.log"
        self._out = self.log.open("wb")
        self.proc = subprocess.Popen(
            [binary, "-db", "-f", str(cfg)], stdout=self._out, stderr=subprocess.STDOUT
        )
        deadline = time.monotonic() + 20
        seen: set[str | None] = set()  # until both replicas have answered through it
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"haproxy exited {self.proc.returncode}: {self.output()}")
            try:
                r = httpx.get(self.url + "/readyz", timeout=2)
                if r.status_code == 200:
                    seen.add(r.headers.get("x-hmpf-replica"))
                    if {"replica1", "replica2"} <= seen:
                        return
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        self.stop()
        raise AssertionError(f"haproxy not balancing after 20 s ({seen}): {self.output()}")


@pytest.fixture(scope="module")
def balancer(
    haproxy_bin: str, replicas: list[Server], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Balancer]:
    lb = Balancer(haproxy_bin, replicas, tmp_path_factory.mktemp("haproxy"))
    yield lb
    lb.stop()


@pytest.fixture(scope="module")
def frames(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "night_right").iterdir())[:N_REFS]


def metric(server: Server, name: str, **labels: str) -> float:
    """The sum of ``name``'s samples in ``server``'s /metrics whose labels include
    ``labels``."""
    return metric_sum(httpx.get(server.url + "/metrics", timeout=10).text, name, **labels)


def answered(server: Server, status: str = "200") -> float:
    return metric(server, "hmpf_requests_total", route="/v1/localize", method="POST", status=status)


def localize_requests(server: Server) -> float:
    return metric(server, "hmpf_requests_total", route="/v1/localize", method="POST")


def test_load_spreads_over_both_replicas(balancer, replicas, keys, frames) -> None:
    before = [answered(s) for s in replicas]
    versions: Counter[str] = Counter()
    lock = threading.Lock()

    def worker(seed: int) -> None:
        with Client(balancer.url, keys["vehicle"], timeout=30, retries=3) as client:
            for k in range(20):
                version = client.localize(frames[(seed + 3 * k) % len(frames)]).index_version
                with lock:
                    versions[version] += 1

    with ThreadPoolExecutor(3) as pool:
        for f in [pool.submit(worker, s) for s in range(3)]:
            f.result()  # raises unless every answer was a 200
    delta = [answered(s) - b for s, b in zip(replicas, before, strict=True)]
    assert sum(delta) == 60 and versions == {"v0001": 60}, (delta, versions)
    assert min(delta) >= 15, f"load not spread: {delta}"


def test_a_json_4xx_is_not_retried(balancer, replicas, keys) -> None:
    before = sum(localize_requests(s) for s in replicas)
    with Client(balancer.url, keys["vehicle"], retries=3, backoff=0.05) as client:
        with pytest.raises(ServiceError) as bad_image:
            client.localize(b"this is not an image")
    with Client(balancer.url, "not-a-key", retries=3, backoff=0.05) as client:
        with pytest.raises(ServiceError) as bad_key:
            client.localize(b"\xff\xd8\xff not even a jpeg")
    assert 400 <= bad_image.value.status < 500 and bad_image.value.body["error"]["code"]
    assert bad_key.value.status == 401 and bad_key.value.code == "unauthorized"
    # one request each reached a replica: neither was sent again
    assert sum(localize_requests(s) for s in replicas) - before == 2


def test_a_vehicle_track_continues_across_replicas(balancer, replicas, keys, frames) -> None:
    refused = sum(metric(s, "hmpf_sequence_refused_total") for s in replicas)
    tracking = [metric(s, "hmpf_sequence_frames_total", status="tracking") for s in replicas]
    # each frame to the other replica directly, the previous answer's token with it
    direct = [Client(s.url, keys["vehicle"], retries=0) for s in replicas]
    statuses, counts, track = [], [], None
    try:
        for i in range(6):
            answer = direct[i % 2].localize(
                frames[5 + i], vehicle_id="car-7", timestamp=float(i), track=track
            )
            assert answer.sequence is not None
            statuses.append(answer.sequence.status)
            counts.append(answer.sequence.frames)
            track = answer.sequence.track
    finally:
        for c in direct:
            c.close()
    assert statuses == ["started"] + ["tracking"] * 5 and counts == [1, 2, 3, 4, 5, 6], (
        statuses,
        counts,
    )
    middle = [metric(s, "hmpf_sequence_frames_total", status="tracking") for s in replicas]
    assert [m - t for m, t in zip(middle, tracking, strict=True)] == [2, 3]
    # through the balancer: the client carries the token, whichever replica answers
    with Client(balancer.url, keys["vehicle"]) as client:
        seen = [
            client.localize(frames[8 + i], vehicle_id="car-8", timestamp=float(i)).sequence
            for i in range(6)
        ]
    assert [s.status for s in seen if s] == ["started"] + ["tracking"] * 5
    after = [metric(s, "hmpf_sequence_frames_total", status="tracking") for s in replicas]
    gained = [a - m for a, m in zip(after, middle, strict=True)]
    assert sum(gained) == 5 and min(gained) >= 1, gained  # both replicas continued the track
    assert sum(metric(s, "hmpf_sequence_refused_total") for s in replicas) == refused


class Load:
    """Clients querying through the balancer in threads until stopped; every outcome kept."""

    def __init__(self, url: str, key: str, frames: list[Path], threads: int, **client: Any):
        self.errors: list[BaseException] = []
        self.versions: Counter[str] = Counter()
        self.done = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._limit: int | None = client.pop("requests", None)
        self._threads = [
            threading.Thread(target=self._loop, args=(url, key, frames, i, client))
            for i in range(threads)
        ]
        for t in self._threads:
            t.start()

    def _loop(self, url: str, key: str, frames: list[Path], seed: int, kw: Any) -> None:
        with Client(url, key, **kw) as client:
            k = seed
            while not self._stop.is_set():
                with self._lock:
                    if self._limit is not None and self.done >= self._limit:
                        return
                try:
                    version = client.localize(frames[k % len(frames)]).index_version
                except Exception as exc:
                    with self._lock:
                        self.errors.append(exc)
                else:
                    with self._lock:
                        self.versions[version] += 1
                        self.done += 1
                k += 7

    def stop(self) -> None:
        self._stop.set()
        self.join()

    def join(self) -> None:
        for t in self._threads:
            t.join(120)


def _wait(what: str, predicate: Any, deadline_s: float = SWITCH_DEADLINE_S) -> float:
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > deadline_s:
            raise AssertionError(f"{what}: not within {deadline_s} s")
        time.sleep(0.1)
    return time.monotonic() - start


def _versions(replicas: list[Server], key: str) -> list[tuple[str, str | None]]:
    out = []
    for s in replicas:
        body = httpx.get(s.url + "/v1/index", headers={"X-API-Key": key}, timeout=10).json()
        out.append((body["version"], body["current"]))
    return out


def test_index_use_reaches_every_replica_without_a_failed_request(
    balancer, replicas, index, keys, frames
) -> None:
    assert _versions(replicas, keys["vehicle"]) == [("v0001", "v0001")] * 2
    load = Load(balancer.url, keys["vehicle"], frames, threads=2, retries=3, timeout=30)
    try:
        _wait("load running", lambda: load.done >= 4)
        switch = subprocess.run(
            [sys.executable, "-m", "indexer.cli", "use", "--index", str(index), "v0002"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert switch.returncode == 0, switch.stderr
        took = _wait(
            "both replicas on v0002",
            lambda: _versions(replicas, keys["vehicle"]) == [("v0002", "v0002")] * 2,
        )
        n = load.done
        _wait("queries on v0002", lambda: load.done >= n + 4)
    finally:
        load.stop()
    assert not load.errors, load.errors[:3]
    assert load.versions["v0001"] > 0 and load.versions["v0002"] > 0, load.versions
    assert took < 10, f"the switch took {took:.1f} s"
    for s in replicas:
        assert metric(s, "hmpf_index_info", version="v0002") == 1
        assert metric(s, "hmpf_index_info", version="v0001") == 0
        assert metric(s, "hmpf_index_behind") == 0
        assert metric(s, "hmpf_index_reloads_total", trigger="watch") == 1
        assert metric(s, "hmpf_index_reload_failures_total") == 0


def test_an_unusable_version_is_reported_and_not_served(balancer, replicas, index, keys) -> None:
    """CURRENT names a corrupt copy: both replicas keep v0002 and say so; a reload through
    the balancer is a 409 (not retried); CURRENT back on v0002: nothing behind."""
    use(index, "v0002")  # where the test before left it (or this test alone: switch now)
    _wait("both on v0002", lambda: _versions(replicas, keys["vehicle"]) == [("v0002",) * 2] * 2)
    broken = index / "v0003"
    shutil.copytree(index / "v0002", broken)
    listed = layout.read_manifest(broken)["files"]
    data = broken / max(listed, key=lambda rel: listed[rel]["bytes"])  # the largest data file
    raw = bytearray(data.read_bytes())
    raw[-8:] = bytes(b ^ 0xFF for b in raw[-8:])  # same size, other content
    data.write_bytes(bytes(raw))
    layout.set_current(index, "v0003")  # as a careless writer would: unverified
    try:
        _wait(
            "both replicas report the failure",
            lambda: all(
                metric(s, "hmpf_index_reload_failures_total", trigger="watch") == 1
                for s in replicas
            ),
        )
        assert _versions(replicas, keys["vehicle"]) == [("v0002", "v0003")] * 2
        for s in replicas:
            assert metric(s, "hmpf_index_behind") == 1
            assert metric(s, "hmpf_index_info", version="v0002") == 1
        with Client(balancer.url, keys["vehicle"]) as client:
            assert client.index().version == "v0002"
        before = sum(metric(s, "hmpf_requests_total", route="/v1/index/reload") for s in replicas)
        r = httpx.post(
            balancer.url + "/v1/index/reload", headers={"X-API-Key": keys["admin"]}, timeout=60
        )
        assert r.status_code == 409 and r.json()["error"]["code"] == "index_unusable", r.text
        assert "kept version v0002" in r.json()["error"]["message"]
        after = sum(metric(s, "hmpf_requests_total", route="/v1/index/reload") for s in replicas)
        assert after - before == 1
        # the admin command that posts the reload to every replica directly says so too
        refused = _reload_all(replicas, keys)
        # one line per replica, "URL: STATUS BODY" (a port may itself contain "409")
        statuses = [line.split(": ", 1)[1].split(" ", 1)[0] for line in refused.stdout.splitlines()]
        assert refused.returncode == 1 and statuses == ["409", "409"], refused.stdout
    finally:
        use(index, "v0002")
    for s in replicas:
        assert metric(s, "hmpf_index_behind") == 0  # checked at each scrape
    assert _versions(replicas, keys["vehicle"]) == [("v0002", "v0002")] * 2
    done = _reload_all(replicas, keys)
    assert done.returncode == 0 and done.stdout.count("v0002 -> v0002") == 2, done.stdout


def _reload_all(replicas: list[Server], keys: dict[str, str]) -> subprocess.CompletedProcess[str]:
    key_file = Path(keys["file"]).with_name("admin.key")
    key_file.write_text(keys["admin"] + "\n")
    return subprocess.run(
        [sys.executable, "-m", "service.replicas", "reload", "--key-file", str(key_file)]
        + [s.url for s in replicas],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _free_ports(n: int) -> int:
    """A port P with P..P+n-1 all free on loopback now."""
    for _ in range(100):
        port = free_port()
        try:
            for p in range(port, port + n):
                with socket.socket() as sock:
                    sock.bind(("127.0.0.1", p))
        except OSError:
            continue
        return port
    raise AssertionError(f"no {n} consecutive free ports found")


def test_the_launcher_runs_replicas_behind_haproxy(haproxy_bin, index, tmp_path) -> None:
    """``hmpf-serve replicas run``: N replicas and HAProxy, all stopped on SIGTERM."""
    port = _free_ports(3)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_")}
    env.update({"HMPF_AUTH": "false", "HMPF_WORKERS": "1"})
    for k in ("HMPF_DATASETS", "HMPF_CACHE_DIR"):
        if k in os.environ:
            env[k] = os.environ[k]
    log = (tmp_path / "run.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "replicas", "run", "--index", str(index)]
        + ["--replicas", "2", "--bind", f"127.0.0.1:{port}", "--haproxy", haproxy_bin]
        + ["--out", str(tmp_path / "lb")],
        cwd=ROOT,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group: a failed test stops its children too
    )
    url = f"http://127.0.0.1:{port}"
    try:
        served_by: Counter[str | None] = Counter()

        def both_serve() -> bool:  # HAProxy puts a replica in after 2 good checks (1 s apart)
            if proc.poll() is not None:
                log.flush()
                out = (tmp_path / "run.log").read_text(errors="replace")[-3000:]
                raise AssertionError(f"the launcher exited {proc.returncode}: {out}")
            try:
                r = httpx.get(url + "/v1/index", timeout=5)
            except httpx.TransportError:
                return False
            if r.status_code == 200:
                served_by[r.headers.get("x-hmpf-replica")] += 1
            return {"replica1", "replica2"} <= set(served_by)

        _wait("both of the launcher's replicas serving", both_serve, 90)
        assert set(served_by) == {"replica1", "replica2"}, served_by
        version = httpx.get(url + "/v1/index", timeout=10).json()["version"]
        assert version == layout.current_version(index)
        proc.terminate()
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                pass
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # whatever of the group is left
        proc.wait()
        log.close()
    out = (tmp_path / "run.log").read_text(errors="replace")
    assert "2 replicas on ports" in out and "Traceback" not in out, out[-3000:]
    for i in (1, 2):  # every replica stopped with it
        with pytest.raises(httpx.TransportError):
            httpx.get(f"http://127.0.0.1:{port + i}/readyz", timeout=2)


def test_a_replica_killed_under_load_loses_no_request(balancer, replicas, keys, frames) -> None:
    survivor, victim = replicas
    start = answered(survivor)
    load = Load(
        balancer.url,
        keys["vehicle"],
        frames,
        threads=3,
        requests=60,
        retries=6,
        backoff=0.2,
        max_backoff=2.0,
        timeout=30,
    )
    try:
        _wait("load on both replicas", lambda: load.done >= 12)
        victim_answered = answered(victim)
        victim.proc.kill()  # SIGKILL: requests in flight on it are cut
        victim.proc.wait(10)
        # from here on only the survivor can answer (survivor first: an answer it counts
        # before this read and a client gets after the next one straddles; one per thread)
        survivor_at_kill = answered(survivor)
        done_at_kill = load.done
        load.join()
    finally:
        load.stop()
    assert not load.errors, load.errors[:3]
    assert load.done >= 60 and load.done - done_at_kill >= 20, (load.done, done_at_kill)
    assert victim_answered > 0 and survivor_at_kill > start
    assert answered(survivor) - survivor_at_kill >= load.done - done_at_kill - 3
    _wait("haproxy marks the replica down", lambda: "is DOWN" in balancer.output(), 10)
    assert re.search(r"replica2 is DOWN", balancer.output()), balancer.output()
