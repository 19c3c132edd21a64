"""Region shards on Ray Serve (:mod:`service.ray_shards`), on a local Ray cluster the test
starts (2 CPUs, loopback) and shuts down: a real index of Gardens Point day_left (34 places,
GeM and Gist in tier 1, HOG and SAD deciding) split into two shards (the second with two
replicas), served by the router over HTTP; answers compared with ``hmpf-serve``'s app over
the unsharded index (the same requests, through its HTTP interface):

* every night_right frame, single frame, and a GPS-prior frame: equal answers; the same
  places and thumbnails;
* sequence mode: the same estimates, frame after frame, with the client keeping the track;
* bad input: the same JSON 4xx;
* one replica of a shard killed: every request still answered (the router sends a call
  whose replica died again), and Ray Serve starts a replacement;
* a new version of one shard, rolled out by redeploying it: both of its replicas switch,
  the router reloads the map (a client retries the one 503 ``shard_changed``), the answers
  stay equal, and a vehicle's track from before restarts (``index_changed``).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from hmpf.client import Client
from hmpf.config import parse_config
from hmpf.index import layout
from indexer.build import build
from indexer.shard import split
from service.app import create_app
from service.settings import load_settings
from tests.conftest import BASE_LAT, BASE_LON, STEP_LAT, copy_gp, write_positions
from tests.service_helpers import BUILD_OPTIONS, free_port

ray = pytest.importorskip("ray")
serve = pytest.importorskip("ray.serve")

N = 34
CONFIG = {
    "name": "ray-shards-test",
    "tiers": [{"methods": ["gem", "gist"], "k": 5}, {"methods": ["hog", "sad"], "k": 1}],
    "sequence": {"lock_mass": 0.9},
}
KEY = "k" * 32
APP = "hmpf"


@pytest.fixture(scope="module")
def maps(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("ray-shards")
    refs = copy_gp(gardens_point, "day_left", base / "refs", N)
    csv = write_positions(refs, base / "meta.csv")
    index = base / "index"
    build(parse_config(CONFIG), refs, index, metadata=csv, options=BUILD_OPTIONS)
    out = base / "shards"
    split(index, 2, 3, out)
    return {"index": index, "shards": out}


@pytest.fixture(scope="module")
def frames(gardens_point: Path) -> list[bytes]:
    return [p.read_bytes() for p in sorted((gardens_point / "night_right").iterdir())[:N]]


def _settings(**extra: Any) -> dict[str, Any]:
    return {"auth": False, "workers": 1, "sequence_key": KEY, **extra}


@pytest.fixture(scope="module")
def whole(maps: dict[str, Path]) -> Iterator[TestClient]:
    """``hmpf-serve``'s app over the unsharded index."""
    settings = load_settings(None, index=maps["index"], **_settings())
    with TestClient(create_app(settings)) as client:
        yield client


def _deploy(folder: Path, versions: dict[str, str] | None = None) -> None:
    from service.ray_shards import deployment_app

    app = deployment_app(
        folder, replicas_of={"shard-01": 2}, versions=versions, settings=_settings()
    )
    serve.run(app, name=APP, route_prefix="/")


@pytest.fixture(scope="module")
def cluster(maps: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A local Ray cluster (2 CPUs, loopback), the shards deployed; the router's URL."""
    temp = tmp_path_factory.mktemp("ray")
    try:
        ray.init(
            num_cpus=2,
            include_dashboard=False,
            _node_ip_address="127.0.0.1",
            _temp_dir=str(temp),
            runtime_env={"env_vars": {"OMP_NUM_THREADS": "1"}},
            log_to_driver=False,
        )
        port = free_port()
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        _deploy(maps["shards"])
        yield f"http://127.0.0.1:{port}"
    finally:
        if ray.is_initialized():
            serve.shutdown()
        ray.shutdown()
        shutil.rmtree(temp, ignore_errors=True)  # Ray's session logs and spilled objects


def _clean(answer: dict[str, Any]) -> dict[str, Any]:
    """An answer without what differs between any two servers: times, the version's name and
    the track token (signed over the version)."""
    answer = json.loads(json.dumps(answer))
    answer.pop("timing_ms", None)
    answer.pop("index_version", None)
    for tier in answer.get("tiers", []):
        tier.pop("time_ms", None)
    if answer.get("sequence"):
        answer["sequence"].pop("track", None)
    return answer


def _post(client: Any, data: bytes, **params: Any) -> httpx.Response:
    return client.post(
        "/v1/localize", content=data, params=params, headers={"content-type": "image/jpeg"}
    )


def test_answers_equal_unsharded_over_http(
    cluster: str, whole: TestClient, frames: list[bytes]
) -> None:
    with httpx.Client(base_url=cluster, timeout=60) as sharded:
        info = sharded.get("/v1/index").json()
        assert info["references"] == N
        assert info["version"] == "shard-00@v0001+shard-01@v0001"
        for i, data in enumerate(frames):
            a, b = _post(whole, data, top_k=5), _post(sharded, data, top_k=5)
            assert a.status_code == b.status_code == 200
            assert _clean(a.json()) == _clean(b.json()), f"frame {i}"
        # a GPS prior around place 25 (shard 01 only)
        prior = {"lat": BASE_LAT + 25 * STEP_LAT, "lon": BASE_LON, "radius_m": 30.0}
        a, b = _post(whole, frames[25], **prior), _post(sharded, frames[25], **prior)
        assert a.json()["prior"]["references"] < N
        assert _clean(a.json()) == _clean(b.json())
        # bad input: the same JSON errors
        for data, params in ((b"not an image", {}), (frames[0], {"top_k": 0})):
            a, b = _post(whole, data, **params), _post(sharded, data, **params)
            assert 400 <= a.status_code < 500 and a.status_code == b.status_code
            assert a.json() == b.json()
        r = sharded.post("/v1/localize/batch", content=b"x", headers={"content-type": "text/a"})
        assert r.status_code == 415 and r.json()["error"]["code"] == "unsupported_media_type"
        # the places and their thumbnails (read from the owning shard)
        a, b = whole.get("/v1/references").json(), sharded.get("/v1/references").json()
        a.pop("index_version"), b.pop("index_version")
        assert a == b and b["thumbnails"]
        for ref in (2, 20, 33):
            a, b = (c.get(f"/v1/references/{ref}/thumbnail") for c in (whole, sharded))
            assert b.status_code == 200 and a.content == b.content
        assert sharded.get(f"/v1/references/{N}/thumbnail").status_code == 404


def test_sequence_mode_across_shards(cluster: str, whole: TestClient, frames: list[bytes]) -> None:
    tracks: dict[str, str] = {}
    with httpx.Client(base_url=cluster, timeout=60) as sharded:
        locked = 0
        for i in range(4, 24):
            answers = []
            for name, client in (("whole", whole), ("sharded", sharded)):
                headers = {"content-type": "image/jpeg", "X-Vehicle-Id": "car-1"}
                if name in tracks:
                    headers["X-Track"] = tracks[name]
                r = client.post("/v1/localize", content=frames[i], headers=headers)
                assert r.status_code == 200, r.text
                tracks[name] = r.json()["sequence"]["track"]
                answers.append(_clean(r.json()))
            assert answers[0] == answers[1], f"frame {i}"
            assert answers[0]["sequence"]["status"] != "reset" or i == 4
            locked += answers[0]["sequence"]["locked"]
        assert locked > 0  # the filter did lock on in both


def _replicas(deployment: str) -> list[str]:
    names = ray.util.list_named_actors(all_namespaces=True)
    return sorted(
        a["name"] for a in names if a["name"].startswith(f"SERVE_REPLICA::{APP}#{deployment}#")
    )


def test_killed_replica_recovers_without_failed_request(
    cluster: str, whole: TestClient, frames: list[bytes]
) -> None:
    before = _replicas("shard-01")
    assert len(before) == 2
    victim = ray.get_actor(before[0], namespace="serve")
    order = [i % N for i in range(0, 3 * N, 2)]
    got: dict[int, Any] = {}
    failed: list[BaseException] = []

    def vehicle() -> None:  # frames sent one after another while the replica is killed
        with Client(cluster, retries=3, backoff=0.5) as client:
            for k, i in enumerate(order):
                try:
                    got[k] = client.localize(frames[i], top_k=5).model_dump(mode="json")
                except BaseException as exc:  # noqa: BLE001 - recorded, asserted below
                    failed.append(exc)

    sender = threading.Thread(target=vehicle)
    sender.start()
    while len(got) < 3 and sender.is_alive():
        time.sleep(0.01)
    ray.kill(victim, no_restart=True)
    sender.join(timeout=120)
    assert not sender.is_alive() and failed == [] and len(got) == len(order)
    for k, i in enumerate(order):  # every request answered, the same answer
        assert _clean(got[k]) == _clean(_post(whole, frames[i], top_k=5).json()), f"frame {i}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        now = _replicas("shard-01")
        if len(now) == 2 and before[0] not in now:
            break
        time.sleep(1)
    assert len(now) == 2 and before[0] not in now, now  # a replacement started


def _new_version(root: Path) -> str:
    """A new version of a shard: its current one republished under the next name."""
    old = layout.current_version(root)
    assert old is not None
    new = layout.next_version_name(root)
    shutil.copytree(root / old, root / new)
    manifest = json.loads((root / new / layout.MANIFEST).read_text())
    manifest["version"] = new
    layout.write_manifest(root / new, manifest)
    layout.set_current(root, new)
    return new


def test_reload_of_one_shard_reaches_its_replicas(
    cluster: str, maps: dict[str, Path], whole: TestClient, frames: list[bytes]
) -> None:
    seq = {"content-type": "image/jpeg", "X-Vehicle-Id": "car-2"}
    with httpx.Client(base_url=cluster, timeout=60) as c:
        r = c.post("/v1/localize", content=frames[10], headers=seq)
        assert r.status_code == 200
        token = r.json()["sequence"]["track"]  # a track on the versions before
    new = _new_version(maps["shards"] / "shard-01")
    _deploy(maps["shards"], versions={"shard-01": new})
    handle = serve.get_deployment_handle("shard-01", app_name=APP)
    seen = {}
    for _ in range(40):
        d = handle.describe.remote().result()
        seen[d["replica"]] = d["version"]
    assert set(seen.values()) == {new} and len(seen) == 2, seen
    with Client(cluster, retries=4, backoff=0.5) as client:
        for i in (1, 17, 30):
            got = client.localize(frames[i], top_k=5).model_dump(mode="json")
            assert got["index_version"] == f"shard-00@v0001+shard-01@{new}"
            assert _clean(got) == _clean(_post(whole, frames[i], top_k=5).json())
    assert os.path.isdir(maps["shards"] / "shard-01" / new)
    assert np.isfinite(got["match"]["score"])
    # the vehicle's next frame: its track restarts on the new map, as on a new version
    with httpx.Client(base_url=cluster, timeout=60) as c:
        r = c.post("/v1/localize", content=frames[11], headers={**seq, "X-Track": token})
        assert r.status_code == 200
        assert r.json()["sequence"]["reset_reason"] == "index_changed"
