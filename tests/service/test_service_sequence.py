"""Sequence mode of ``/v1/localize`` (``vehicle_id`` + ``track`` + ``timestamp``) and
``hmpf-replay``, on a real index (Gardens Point day_right, 100 references) with real night
frames; no mocks.

* a night drive locks on and follows the route; dropped frames (timestamps) are counted;
* refused tokens (altered, truncated, garbage, another vehicle's) are a JSON 422;
* an expired token and a token of another index version restart the track, with the reason;
* a frame older than the token is answered single-frame, its token handed back unchanged;
* a batch runs the filter over its frames in order, a bad image counting as a dropped frame;
* the metrics count it all; no answer is a 5xx;
* end to end: a real ``hmpf-serve`` restarted mid-drive continues the track (no reset), as
  played by ``hmpf-replay``.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import re
import shutil
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from hmpf.cli.replay import Vehicle, build_parser, replay, select_frames
from hmpf.cli.replay import main as replay_main
from hmpf.errors import ConfigError
from indexer.build import remove
from service.app import create_app
from service.auth import add_key
from service.settings import load_settings
from service.track import (
    KEY_FILE,
    MAX_TOKEN_CHARS,
    TokenCodec,
    Track,
    TrackRefused,
    frame_steps,
    load_or_create_key,
)
from tests.service_helpers import BUILD_OPTIONS, GP_CONFIG, Server, build_gp_index, free_port

N_REFS = 100
#: The end-to-end hierarchy with the lock threshold an operator of this short map would set:
#: the default (0.99, chosen for 99 % precision on the shared routes' training drives with
#: their hierarchies) is not reached by this hierarchy on this stretch (its mass settles at
#: about 0.98), and these tests are about what the service does around a lock.
SEQ_CONFIG = {**GP_CONFIG, "sequence": {"lock_mass": 0.9}}
#: The night drive: night_right frames 40..65 against day_right 0..99 (frame-aligned).
DRIVE = range(40, 66)
FPS = 2.0  # the drive's timestamps: frame i at i / FPS seconds


@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_gp_index(gardens_point, tmp_path_factory.mktemp("seq"), N_REFS, SEQ_CONFIG)


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("seq-keys") / "keys.yaml"
    return {
        "file": str(path),
        "vehicle": add_key(path, "car", "vehicle"),
        "admin": add_key(path, "ops", "admin"),
    }


def _client(index: Path, keys: dict[str, str], **overrides: Any) -> TestClient:
    """A TestClient; two workers, so that a batch runs in two lanes."""
    settings = load_settings(
        None, index=index, keys_file=keys["file"], workers=2, queue=4, max_batch=8, **overrides
    )
    return TestClient(create_app(settings))


@pytest.fixture(scope="module")
def client(index: Path, keys: dict[str, str]) -> Iterator[TestClient]:
    with _client(index, keys) as c:
        yield c


@pytest.fixture(scope="module")
def night(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "night_right").iterdir())


class Car:
    """One vehicle's requests through a TestClient; every answer must be below 500."""

    def __init__(self, client: TestClient, keys: dict[str, str], night: list[Path], vid: str):
        self.client, self.night, self.vid = client, night, vid
        self.headers = {"X-API-Key": keys["vehicle"]}

    def post(self, i: int, track: str | None = None, **fields: Any) -> Any:
        data = {"vehicle_id": self.vid, **fields}
        if track is not None:
            data["track"] = track
        path = self.night[i]
        r = self.client.post(
            "/v1/localize",
            files={"image": (path.name, path.read_bytes(), "image/jpeg")},
            data={k: str(v) for k, v in data.items() if v is not None},
            headers=self.headers,
        )
        assert r.status_code < 500, r.text
        return r

    def drive(self, frames: range | list[int], track: str | None = None, timed: bool = True):
        """Answers of ``frames`` in order, each with the previous answer's track."""
        out = []
        for i in frames:
            r = self.post(i, track, timestamp=i / FPS if timed else None)
            assert r.status_code == 200, r.text
            body = r.json()
            track = body["sequence"]["track"]
            out.append(body)
        return out


def _metric(client: TestClient, name: str, **labels: str) -> float:
    text = client.get("/metrics").text
    want = ",".join(f'{k}="{v}"' for k, v in labels.items())
    pattern = rf"^{name}" + (rf"\{{{re.escape(want)}\}}" if want else "") + r" (\S+)$"
    m = re.search(pattern, text, re.MULTILINE)
    return float(m.group(1)) if m else 0.0


def _error(r: Any, status: int, code: str) -> str:
    assert r.status_code == status, r.text
    body = r.json()
    assert set(body) == {"error"} and body["error"]["code"] == code, body
    return str(body["error"]["message"])


# -- the pure parts ------------------------------------------------------------------------------
def test_frame_steps_counts_dropped_frames_from_timestamps() -> None:
    nan = float("nan")
    assert frame_steps(nan, 0.5) == (1, 0.5)  # no time: the next frame
    assert frame_steps(0.0, 0.5) == (0, 0.5)  # the same instant
    assert frame_steps(0.5, nan) == (1, 0.5)  # the first interval is learned
    assert frame_steps(0.5, 0.5) == (1, 0.5)
    steps, interval = frame_steps(2.0, 0.5)  # three frames dropped
    assert steps == 4 and interval == pytest.approx(0.5)
    assert frame_steps(0.55, 0.5)[0] == 1 and frame_steps(0.55, 0.5)[1] > 0.5
    # A first "interval" that was itself a gap is given up at once when frames come faster.
    assert frame_steps(0.5, 2.0) == (1, 0.5)
    assert frame_steps(1e12, 0.5)[0] == 10_000  # bounded


def test_token_round_trip_and_refusals() -> None:
    codec = TokenCodec(b"k" * 32)
    from service.track import vehicle_digest

    track = Track(b"b" * 8, vehicle_digest("car-1"), 1.5e9, 12.5, 0.5, b"state-bytes")
    token = codec.encode(track)
    assert codec.decode(token, "car-1") == track
    assert codec.encode(codec.decode(token, "car-1")) == token
    raw = base64.urlsafe_b64decode(token + "=" * (-len(token) % 4))
    for i in (5, len(raw) - 1):  # a byte of the payload, of the signature
        bad = bytearray(raw)
        bad[i] ^= 1
        forged = base64.urlsafe_b64encode(bytes(bad)).rstrip(b"=").decode()
        with pytest.raises(TrackRefused) as exc:
            codec.decode(forged, "car-1")
        assert exc.value.reason == "signature"
    for junk in ("", token[:30], token + "=", token + "A", "not a token!", "é" * 10):
        with pytest.raises(TrackRefused) as exc:
            codec.decode(junk, "car-1")
        assert exc.value.reason in ("malformed", "signature"), junk
    with pytest.raises(TrackRefused) as exc:
        codec.decode(token, "car-2")
    assert exc.value.reason == "vehicle"
    with pytest.raises(TrackRefused):  # another key
        TokenCodec(b"x" * 32).decode(token, "car-1")


def test_key_file_is_created_once_private_and_shared(tmp_path: Path) -> None:
    path = tmp_path / KEY_FILE
    keys: list[bytes] = []
    threads = [
        threading.Thread(target=lambda: keys.append(load_or_create_key(path))) for _ in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(keys)) == 1 and len(keys[0]) == 32  # every racer reads the same key
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left
    path.write_text("short\n")
    with pytest.raises(ConfigError, match="64 hex digits"):
        load_or_create_key(path)
    with pytest.raises(ConfigError, match="HMPF_SEQUENCE_KEY"):
        load_or_create_key(tmp_path / "missing-dir" / KEY_FILE)


# -- through the API -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def night_drive(client, keys, night) -> list[dict[str, Any]]:
    return Car(client, keys, night, "night-1").drive(DRIVE)


def test_night_drive_locks_on_and_follows_the_route(client, night_drive) -> None:
    statuses = [b["sequence"]["status"] for b in night_drive]
    assert statuses == ["started"] + ["tracking"] * (len(DRIVE) - 1)
    seq_err = [abs(b["match"]["reference_id"] - i) for i, b in zip(DRIVE, night_drive, strict=True)]
    single_err = [
        abs(b["single"]["reference_id"] - i) for i, b in zip(DRIVE, night_drive, strict=True)
    ]
    locked = [b["sequence"]["locked"] for b in night_drive]
    # Measured: locked from the 2nd frame on, every answer within +-2 frames (on this easy
    # stretch the single-frame match is too; over the whole route, 200 frames against 200
    # references: single 164, answer 196 within +-2); the filter step takes about 0.6 ms.
    assert all(locked[3:]), [round(b["sequence"]["mass"], 4) for b in night_drive]
    assert all(e <= 2 for e in seq_err[-10:]), seq_err
    assert sum(e <= 2 for e in seq_err) >= sum(e <= 2 for e in single_err), (seq_err, single_err)
    # In sequence mode the estimate is the answer from the first frame on (accepted when
    # locked); the single-frame match rides along.
    assert all(b["match_source"] == "sequence" for b in night_drive)
    assert all(b["match"] == b["sequence"]["match"] for b in night_drive)
    last = night_drive[-1]
    est = last["sequence"]["match"]
    assert est["score"] is None and est["accepted"] is True
    assert est["confidence"] == last["sequence"]["mass"] >= 0.5
    assert last["sequence"]["frames"] == len(DRIVE) and last["sequence"]["speed"] == 1.0
    assert last["sequence"]["steps"] == 1 and last["single"]["score"] is not None
    assert last["timing_ms"]["sequence"] < 50
    token = last["sequence"]["track"]
    assert len(token) <= MAX_TOKEN_CHARS  # measured: 628 characters (471 bytes)
    assert _metric(client, "hmpf_sequence_answers_total", locked="true") >= len(DRIVE) - 3


def test_openapi_documents_sequence_mode(client) -> None:
    doc = client.get("/openapi.json").json()
    schemas = doc["components"]["schemas"]
    post = doc["paths"]["/v1/localize"]["post"]
    params = {(p["in"], p["name"]): p for p in post["parameters"]}
    for where, name in (("header", "X-Vehicle-Id"), ("header", "X-Track"), ("query", "timestamp")):
        assert "sequence mode" in params[where, name]["description"], name
    # never in the URL (it ends up in logs)
    assert not {("query", "vehicle_id"), ("query", "track")} & set(params)
    answer = schemas["LocalizeResponse"]["properties"]
    assert {"match", "match_source", "single", "sequence"} <= set(answer)
    assert "locked" in answer["match"]["description"]
    report = schemas["SequenceReport"]["properties"]
    assert set(report) == {
        "status", "reset_reason", "match", "mass", "locked", "off_map", "off_map_probability",
        "frames", "speed", "steps", "track",
    }  # fmt: skip
    assert all(p.get("description") for p in report.values())
    assert "track" in schemas["BatchResponse"]["properties"]


def test_single_frame_answers_without_vehicle(client, keys, night) -> None:
    path = night[45]
    r = client.post(
        "/v1/localize",
        files={"image": (path.name, path.read_bytes(), "image/jpeg")},
        headers={"X-API-Key": keys["vehicle"]},
    )
    body = r.json()
    assert body["sequence"] is None and body["match_source"] == "single"
    assert body["match"] == body["single"]
    for fields in ({"track": "abc"}, {"timestamp": "1.0"}):  # sequence fields need a vehicle
        r = client.post(
            "/v1/localize",
            files={"image": (path.name, path.read_bytes(), "image/jpeg")},
            data=fields,
            headers={"X-API-Key": keys["vehicle"]},
        )
        assert "vehicle_id" in _error(r, 422, "invalid_request")


def _flip(token: str, i: int) -> str:
    raw = bytearray(base64.urlsafe_b64decode(token + "=" * (-len(token) % 4)))
    raw[i] ^= 0x40
    return base64.urlsafe_b64encode(bytes(raw)).rstrip(b"=").decode()


def test_refused_tracks_are_422_json(client, keys, night, night_drive) -> None:
    token = night_drive[-1]["sequence"]["track"]
    car = Car(client, keys, night, "night-1")
    cases = [
        (_flip(token, 30), "signature"),  # a byte of the payload (issued_at)
        (_flip(token, 200), "signature"),  # a byte of the filter state
        (_flip(token, -1), "signature"),  # a byte of the signature
        (token[:200], "signature"),  # truncated: decodes, but is not what was signed
        (token[:10], "malformed"),  # too short to be a token
        ("garbage-token", "malformed"),
        ("%%%%", "malformed"),
    ]
    other = Car(client, keys, night, "night-2")
    for who, bad, reason in [(car, *c) for c in cases] + [(other, token, "vehicle")]:
        before = _metric(client, "hmpf_sequence_refused_total", reason=reason)
        message = _error(who.post(66, bad), 422, "invalid_track")
        assert "without track" in message
        assert _metric(client, "hmpf_sequence_refused_total", reason=reason) == before + 1, bad
    assert "another vehicle_id" in _error(other.post(66, token), 422, "invalid_track")
    # Bounded: an over-long token is refused by the field's limit.
    _error(car.post(66, "A" * (MAX_TOKEN_CHARS + 1)), 422, "invalid_request")
    _error(car.post(66, token, timestamp="nan"), 422, "invalid_request")


def test_expired_track_restarts_with_the_reason(client, keys, night, night_drive, index) -> None:
    token = night_drive[-1]["sequence"]["track"]
    codec = TokenCodec(load_or_create_key(index / KEY_FILE))  # the service's key file
    old = codec.decode(token, "night-1")
    stale = codec.encode(dataclasses.replace(old, issued_at=time.time() - 601))
    before = _metric(client, "hmpf_sequence_resets_total", reason="expired")
    body = Car(client, keys, night, "night-1").post(66, stale, timestamp=33.0).json()
    seq = body["sequence"]
    assert seq["status"] == "reset" and seq["reset_reason"] == "expired" and seq["frames"] == 1
    assert seq["track"] != stale
    assert _metric(client, "hmpf_sequence_resets_total", reason="expired") == before + 1
    # The setting decides what is old: a fresh token passes.
    fresh = codec.encode(dataclasses.replace(old, issued_at=time.time() - 5))
    body = Car(client, keys, night, "night-1").post(66, fresh, timestamp=33.0).json()
    assert body["sequence"]["status"] == "tracking"


def test_track_of_another_index_version_restarts(
    index, keys, night, tmp_path: Path, gardens_point
) -> None:
    copy = tmp_path / "index"
    shutil.copytree(index, copy)
    with _client(copy, keys) as c:
        car = Car(c, keys, night, "car-v")
        token = car.drive([50, 51])[-1]["sequence"]["track"]
        remove(copy, ["Image099.jpg"], options=BUILD_OPTIONS)  # publishes v0002
        r = c.post("/v1/index/reload", headers={"X-API-Key": keys["admin"]})
        assert r.status_code == 200 and r.json()["version"] == "v0002", r.text
        body = car.post(52, token, timestamp=52 / FPS).json()
        assert body["index_version"] == "v0002"
        seq = body["sequence"]
        assert seq["status"] == "reset" and seq["reset_reason"] == "index_changed"
        assert seq["frames"] == 1
        # ... and the new token continues on the new version.
        body = car.post(53, seq["track"], timestamp=53 / FPS).json()
        assert body["sequence"]["status"] == "tracking" and body["sequence"]["frames"] == 2
        assert _metric(c, "hmpf_sequence_resets_total", reason="index_changed") == 1


def test_frame_older_than_the_track_is_out_of_order(client, keys, night) -> None:
    car = Car(client, keys, night, "ooo")
    token = car.drive([60, 61, 62])[-1]["sequence"]["track"]
    before = _metric(client, "hmpf_sequence_frames_total", status="out_of_order")
    body = car.post(59, token, timestamp=59 / FPS).json()
    seq = body["sequence"]
    assert seq["status"] == "out_of_order" and seq["track"] == token
    assert seq["match"] is None and seq["locked"] is False and seq["steps"] is None
    assert body["match_source"] == "single" and body["match"] == body["single"]
    assert _metric(client, "hmpf_sequence_frames_total", status="out_of_order") == before + 1
    # The vehicle goes on with the same token, as if the late frame had not come.
    body = car.post(63, token, timestamp=63 / FPS).json()
    assert body["sequence"]["status"] == "tracking" and body["sequence"]["frames"] == 4
    assert body["sequence"]["steps"] == 1
    # The same instant again: the belief does not move.
    again = car.post(63, body["sequence"]["track"], timestamp=63 / FPS).json()
    assert again["sequence"]["steps"] == 0 and again["sequence"]["status"] == "tracking"


def test_dropped_frames_are_counted_and_still_tracked(client, keys, night) -> None:
    car = Car(client, keys, night, "gaps")
    frames = [*range(70, 78), *range(81, 86)]  # 78, 79, 80 dropped
    answers = car.drive(frames)
    steps = [a["sequence"]["steps"] for a in answers]
    assert steps == [1] * 8 + [4] + [1] * 4, steps
    after_gap = answers[8:]
    assert all(a["sequence"]["locked"] for a in after_gap)
    errors = [
        abs(a["match"]["reference_id"] - i) for i, a in zip(frames[8:], after_gap, strict=True)
    ]
    assert all(e <= 2 for e in errors), errors  # measured: every frame after the gap within 1


def test_batch_follows_its_frames_in_order(client, keys, night) -> None:
    headers = {"X-API-Key": keys["vehicle"]}

    def batch(frames: list[int | None], **data: str) -> Any:
        files = [
            ("images", (f"f{k}.jpg", b"not an image" if i is None else night[i].read_bytes()))
            for k, i in enumerate(frames)
        ]
        r = client.post(
            "/v1/localize/batch",
            files=[(n, (f, d, "image/jpeg")) for n, (f, d) in files],
            data={"vehicle_id": "bus", **data},
            headers=headers,
        )
        assert r.status_code < 500, r.text
        return r

    r = batch([20, 21, 22, None, 24, 25])
    assert r.status_code == 200, r.text
    body = r.json()
    items = body["results"]
    assert items[3]["error"]["code"] == "invalid_image" and items[3]["result"] is None
    seqs = [it["result"]["sequence"] for k, it in enumerate(items) if k != 3]
    assert [s["status"] for s in seqs] == ["started"] + ["tracking"] * 4
    assert [s["steps"] for s in seqs] == [1, 1, 1, 2, 1]  # the bad image counts as dropped
    assert [s["frames"] for s in seqs] == [1, 2, 3, 4, 5]
    assert body["track"] == seqs[-1]["track"]
    for s in seqs[:-1]:
        assert s["track"] != body["track"]
    # The next batch continues the track.
    nxt = batch([26, 27], track=body["track"]).json()
    last = nxt["results"][-1]["result"]
    assert last["sequence"]["frames"] == 7 and last["sequence"]["locked"]
    assert abs(last["match"]["reference_id"] - 27) <= 2
    # Timestamps belong to single frames.
    assert "timestamp" in _error(batch([28], timestamp="1.0"), 422, "invalid_request")
    # A batch without a vehicle is not in sequence mode.
    r = client.post(
        "/v1/localize/batch",
        files=[("images", ("a.jpg", night[5].read_bytes(), "image/jpeg"))],
        headers=headers,
    )
    assert r.json()["track"] is None and r.json()["results"][0]["result"]["sequence"] is None


def test_gps_prior_in_sequence_mode(service_index, keys, gardens_point) -> None:
    """The 20-reference index with positions (tests/conftest.py): reference i lies 11 m
    north of i - 1."""
    from tests.conftest import BASE_LAT, BASE_LON, STEP_LAT

    refs = sorted((gardens_point / "day_right").iterdir())
    with _client(service_index, keys) as c:
        headers = {"X-API-Key": keys["vehicle"]}

        def post(i: int, lat: float, track: str | None) -> Any:
            data = {"vehicle_id": "gps", "lat": lat, "lon": BASE_LON, "radius_m": 30.0}
            if track:
                data["track"] = track
            r = c.post(
                "/v1/localize",
                files={"image": ("x.jpg", refs[i].read_bytes(), "image/jpeg")},
                data=data,
                headers=headers,
            )
            assert r.status_code == 200, r.text
            return r.json()

        track = None
        for i in range(8, 12):
            body = post(i, BASE_LAT + i * STEP_LAT, track)
            track = body["sequence"]["track"]
            assert body["prior"]["applied"] and body["prior"]["references"] < 20
            assert abs(body["match"]["reference_id"] - i) <= 2
            assert abs(body["sequence"]["match"]["lat"] - (BASE_LAT + i * STEP_LAT)) < 3 * STEP_LAT
        # A prior far from every reference: no evidence, the track goes on (motion only).
        body = post(12, BASE_LAT + 1.0, track)
        assert body["single"] is None and body["sequence"]["status"] == "tracking"
        assert body["sequence"]["frames"] == 5


def test_key_from_settings_and_a_key_that_cannot_be_made(
    service_index, keys, gardens_point, tmp_path
) -> None:
    path = sorted((gardens_point / "day_right").iterdir())[3]
    files = {"image": (path.name, path.read_bytes(), "image/jpeg")}
    headers = {"X-API-Key": keys["vehicle"]}
    with _client(service_index, keys, sequence_key="a-long-shared-replica-secret") as c:
        token = c.post("/v1/localize", files=files, data={"vehicle_id": "k"}, headers=headers)
        token = token.json()["sequence"]["track"]
    with _client(service_index, keys, sequence_key="a-long-shared-replica-secret") as c:
        r = c.post(
            "/v1/localize", files=files, data={"vehicle_id": "k", "track": token}, headers=headers
        )
        assert r.json()["sequence"]["status"] == "tracking"  # another replica, same key
    with _client(service_index, keys) as c:  # the index's key file: another key
        r = c.post(
            "/v1/localize", files=files, data={"vehicle_id": "k", "track": token}, headers=headers
        )
        _error(r, 422, "invalid_track")
    with _client(service_index, keys, sequence_key_file=tmp_path / "no" / "key") as c:
        r = c.post("/v1/localize", files=files, data={"vehicle_id": "k"}, headers=headers)
        assert "HMPF_SEQUENCE_KEY" in _error(r, 503, "sequence_unavailable")
        r = c.post("/v1/localize", files=files, headers=headers)  # single frames still work
        assert r.status_code == 200


def test_replay_takes_a_key_that_starts_with_a_dash_written_with_equals(tmp_path: Path) -> None:
    """Keys made before they stopped starting with ``-`` still work, as ``--key=KEY`` (what
    the help says); ``--key -X...`` is an option to argparse, an error (exit 2)."""
    args = build_parser().parse_args([str(tmp_path), "--key=-XIH0", "--limit", "1"])
    assert args.key == "-XIH0"
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args([str(tmp_path), "--key", "-XIH0"])
    assert exc.value.code == 2


# -- end to end: a real server, restarted mid-drive, played by hmpf-replay -------------------------
def test_restart_mid_drive_keeps_the_track(
    index, keys, gardens_point, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = gardens_point / "night_right"
    frames = select_frames(folder, 40, 25, 1)
    car = Vehicle("", keys["vehicle"], "e2e-car")
    srv = Server(index, tmp_path / "a.log", keys_file=keys["file"], workers="1")
    try:
        car.url = srv.url
        before = replay(car, frames[:15], fps=20.0)
        # A wrong key: one line, exit 2.
        rc = replay_main([str(folder), "--url", srv.url, "--key", "wrong", "--limit", "1"])
        assert rc == 2
        assert capsys.readouterr().err.strip().startswith("hmpf-replay: error: ")
    finally:
        srv.stop()
    key_file = (index / KEY_FILE).read_bytes()
    srv = Server(index, tmp_path / "b.log", keys_file=keys["file"], workers="1")
    try:
        car.url = srv.url
        after = replay(car, frames[15:], fps=20.0, first=15)
        # The command itself: a faster vehicle (every 2nd frame), answers written as JSON.
        out = tmp_path / "drive.json"
        rc = replay_main(
            [str(folder), "--url", srv.url, "--key", keys["vehicle"], "--vehicle-id", "cli",
             "--start", "40", "--limit", "12", "--every", "2", "--json", str(out)]
        )  # fmt: skip
        lines = capsys.readouterr().out.strip().splitlines()
    finally:
        srv.stop()
    assert (index / KEY_FILE).read_bytes() == key_file  # the restarted server kept the key
    assert all(r.ok for r in before + after)
    assert [r.sequence["status"] for r in after] == ["tracking"] * len(after)  # no reset
    assert after[0].sequence["frames"] == 16 and after[0].sequence["locked"]
    assert after[0].sequence["steps"] == 1  # timestamps went on across the restart
    errors = [abs(r.body["match"]["reference_id"] - r.frame) for r in before[5:] + after]
    assert all(e <= 2 for e in errors), errors
    assert rc == 0 and len(lines) == 13 and lines[-1].startswith("12 frames: 12 answered")
    assert re.match(r"\s*40 Image040\.jpg  single\s+\d+  sequence\s+\d+  mass ", lines[0])
    records = json.loads(out.read_text())
    assert [r["frame"] for r in records] == list(range(40, 64, 2))
    speeds = [r["answer"]["sequence"]["speed"] for r in records[-4:]]
    assert speeds.count(2.0) >= 3, speeds  # the filter sees a vehicle twice as fast
    # The service is gone: one line, exit 2.
    rc = replay_main([str(folder), "--url", srv.url, "--limit", "1"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hmpf-replay: error: cannot reach the service") and "\n" not in err
    assert "Traceback" not in srv.output()


def test_replay_argument_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    assert replay_main([str(tmp_path / "nope"), "--url", url]) == 2
    assert replay_main([str(tmp_path), "--url", url, "--every", "0"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all(e.startswith("hmpf-replay: error: ") for e in err)
