"""Recording accepted frames into the experience log, through a real ``hmpf-serve`` (uvicorn
in a subprocess) on a real index: the default preset (its shipped confidence models) over
Gardens Point day_left, driven by day_right frames in sequence mode (the fleet pass of the
experience loop: the other side of the road).

* the recorded frames are exactly the answers accepted with p_correct >= the threshold in an
  enabled mode, with their place, p_correct, vehicle, timestamp, version and bytes, each
  after its lead-in (the vehicle's last frames not recorded, at most 2, within 30 s);
* recording off records nothing;
* a stuck log (its lock held, as by a long prune) and a log folder that cannot be created
  never fail or hold up an answer: the frames are dropped and counted;
* a kill -9 of the service while it records leaves a readable log, every record intact.

The threshold here is 0.9, not the default 0.99: on this 40-reference stretch the shipped
sequence model's p_correct stays between about 0.84 and 0.98 once locked (measured), and
these tests are about what the service does with the answers it accepts, not about the
model. Drives start at the route's first frame, where the filter locks on at once.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from hmpf.config import load_config
from hmpf.experience_log import ExperienceLog, LogStats, Record, read_log
from hmpf.features import unpack_features
from hmpf.imageio import decode_image
from hmpf.index import IndexReader
from indexer.build import build
from service.metrics import Metrics
from service.recording import Frame, Recorder, recorded_mode
from service.schemas import LocalizeResponse, SequenceReport
from service.settings import load_settings
from tests.conftest import copy_gp
from tests.service_helpers import BUILD_OPTIONS, Server

N_REFS = 32
THRESHOLD = 0.9
#: The recording servers' threshold: above the first frames of the drive below (their
#: p_correct about 0.97 with the default's shipped models), below most of the rest, so that
#: a drive records some of its accepted answers and not all (read from each answer by
#: ``_to_record``, not assumed).
RECORD_AT = 0.985
#: The drive: day_right frames (frame-aligned with day_left), 2 per second.
FPS = 2.0
T0 = 1.7e9  # the vehicles' clock: seconds since the epoch


@pytest.fixture(scope="module")
def index(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("rec")
    refs = copy_gp(gardens_point, "day_left", base / "refs", N_REFS)
    build(load_config("default"), refs, base / "index", options=BUILD_OPTIONS)
    return base / "index"


@pytest.fixture(scope="module")
def frames(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "day_right").iterdir())


def _server(index: Path, log: Path | None, tmp: Path, **env: str) -> Server:
    settings = {"auth": "false", "workers": "1", "experience_min_p_correct": str(RECORD_AT)}
    if log is not None:
        settings["experience_log"] = str(log)
    return Server(index, tmp / "serve.log", **settings, **env)


@pytest.fixture(scope="module")
def recording(index: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server recording sequence-mode answers; every frame its own segment (64 KiB)."""
    tmp = tmp_path_factory.mktemp("rec-on")
    srv = _server(
        index,
        tmp / "experiences",
        tmp,
        experience_segment_bytes=str(64 * 1024),
        experience_max_bytes=str(64 << 20),
        experience_queue="4",  # a lock's frame and its lead-in (3) fit
        experience_sync_every="4",
    )
    srv.experiences = tmp / "experiences"  # type: ignore[attr-defined]
    yield srv
    srv.stop()
    assert "Traceback" not in srv.output()


class Car:
    """One vehicle driving its frames against a server (raw bodies, the vehicle headers)."""

    def __init__(self, url: str, vehicle: str, frames: list[Path]) -> None:
        self.http = httpx.Client(base_url=url, timeout=60)
        self.vehicle, self.frames = vehicle, frames
        self.track: str | None = None
        #: (frame, answer, bytes, timestamp sent) of every frame answered
        self.sent: list[tuple[int, dict[str, Any], bytes, float | None]] = []

    def frame(self, i: int, timed: bool = True) -> dict[str, Any]:
        data = self.frames[i].read_bytes()
        headers = {"Content-Type": "image/jpeg", "X-Vehicle-Id": self.vehicle}
        if self.track:
            headers["X-Track"] = self.track
        ts = T0 + i / FPS if timed else None
        params = {} if ts is None else {"timestamp": ts}
        r = self.http.post("/v1/localize", content=data, headers=headers, params=params)
        assert r.status_code == 200, r.text
        body = r.json()
        self.track = body["sequence"]["track"]
        self.sent.append((i, body, data, ts))
        return dict(body)

    def drive(self, indices: range) -> list[dict[str, Any]]:
        return [self.frame(i) for i in indices]


def _single(url: str, path: Path) -> dict[str, Any]:
    r = httpx.post(
        url + "/v1/localize",
        content=path.read_bytes(),
        headers={"Content-Type": "image/jpeg"},
        timeout=60,
    )
    assert r.status_code == 200, r.text
    return dict(r.json())


def metrics(url: str) -> dict[str, float]:
    """The experience metrics of a server: name (with labels) -> value."""
    text = httpx.get(url + "/metrics", timeout=30).text
    found = re.findall(r"^(hmpf_experience_\w+(?:\{[^}]*\})?) (\S+)$", text, re.M)
    return {k: float(v) for k, v in found}


def _dropped(m: dict[str, float], reason: str) -> float:
    return m[f'hmpf_experience_dropped_total{{reason="{reason}"}}']


def _wait_recorded(url: str, n: float, timeout: float = 20) -> dict[str, float]:
    deadline = time.monotonic() + timeout
    while True:
        m = metrics(url)
        if m["hmpf_experience_recorded_total"] >= n or time.monotonic() > deadline:
            return m
        time.sleep(0.1)


def _settled(url: str, timeout: float = 20) -> dict[str, float]:
    """The metrics once the recorder's queue is empty and its count stays put."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        m = metrics(url)
        if m["hmpf_experience_queue"] == 0 and last == m["hmpf_experience_recorded_total"]:
            return m
        last = m["hmpf_experience_recorded_total"] if m["hmpf_experience_queue"] == 0 else None
        time.sleep(0.3)
    raise AssertionError(f"the recorder did not settle: {metrics(url)}")


def _to_record(body: dict[str, Any]) -> bool:
    """Whether an answer is one the service records here (the rule, read independently)."""
    m = body["match"]
    return bool(
        m is not None
        and m["accepted"]
        and m["p_correct"] is not None
        and m["p_correct"] >= RECORD_AT
        and body["match_source"] == "sequence"
    )


LEADS = 2  # the default experience_lead_frames


def _with_leads(sent: list[tuple[int, dict[str, Any], bytes, float | None]]) -> list[Any]:
    """What one vehicle's answers put in the log, in order (the rule read independently):
    each recorded frame after its lead-in: the last :data:`LEADS` frames not recorded since
    the vehicle's track started or its last off-map answer, if no frame was recorded since,
    taken at most 30 s before it. A batch's frames (``ts`` None) share one received time:
    none leads into another."""
    out: list[Any] = []
    pending: list[Any] = []
    opened = False
    for item in sent:
        _, body, _, ts = item
        report = body["sequence"]
        if _to_record(body):
            out += [
                (lead, "lead")
                for lead in pending[-LEADS:]
                if ts is not None and lead[3] is not None and 0 < ts - lead[3] <= 30
            ]
            out.append((item, "sequence"))
            pending, opened = [], False
        elif body["match"] is None:
            continue
        elif report["off_map"]:
            pending, opened = [], True
        else:
            if report["status"] in ("started", "reset"):
                pending, opened = [], True
            if opened:
                pending.append(item)
    return out


def _read(log: Path) -> tuple[list[Record], LogStats]:
    stats = LogStats()
    return list(read_log(log, stats=stats)), stats


def _answer(p: float | None, accepted: bool, source: str, place: int = 3) -> LocalizeResponse:
    """An answer with just what the recording rule reads."""
    match = {
        "reference_id": place,
        "name": f"Image{place:03d}.jpg",
        "score": None,
        "confidence": 0.5,
        "p_correct": p,
        "accepted": accepted,
        "accepted_by": "p_correct",
    }
    return LocalizeResponse.model_validate(
        {
            "match": match,
            "match_source": source,
            "candidates": [],
            "tiers": [],
            "timing_ms": {},
            "index_version": "v0001",
            "threshold": 2.0,
        }
    )


def test_the_rule_matches_the_settings() -> None:
    """:func:`recorded_mode` is the rule the tests below read independently."""
    s = load_settings(auth=False, experience_min_p_correct=THRESHOLD)
    for p, accepted, source, want in (
        (0.95, True, "sequence", "sequence"),
        (0.89, True, "sequence", None),
        (0.95, False, "sequence", None),
        (None, True, "sequence", None),
        (0.95, True, "single", None),
    ):
        answer = _answer(p, accepted, source)
        assert recorded_mode(answer, s) == want, (p, accepted, source)
        both = load_settings(
            auth=False, experience_min_p_correct=THRESHOLD, experience_modes="sequence,single"
        )
        confident = accepted and p is not None and p >= THRESHOLD
        assert recorded_mode(answer, both) == (source if confident else None)


def test_the_recorder_counts_what_the_bound_drops_and_closes_on_stop(
    frames: list[Path], tmp_path: Path
) -> None:
    """The recorder on its own (no server): a 1 MiB log of 64 KiB segments takes about 20
    frames; more push the oldest segments out, counted as dropped for the bound; stop()
    writes what is queued and lets the log go."""
    log = tmp_path / "experiences"
    s = load_settings(
        auth=False,
        experience_log=log,
        experience_min_p_correct=THRESHOLD,
        experience_max_bytes=2**20,
        experience_segment_bytes=64 * 1024,
        experience_queue=64,
    )
    m = Metrics()
    rec = Recorder(s, m)
    rec.start()
    data = frames[0].read_bytes()
    assert not rec.offer(_answer(0.5, True, "sequence"), data, "image/jpeg", "car", None, 1.0)
    for i in range(40):
        assert rec.offer(_answer(0.95, True, "sequence", i), data, "image/jpeg", "car", None, i)
    rec.stop()
    got, stats = _read(log)
    value = m.registry.get_sample_value
    dropped = value("hmpf_experience_dropped_total", {"reason": "bound"})
    assert value("hmpf_experience_recorded_total") == 40 and dropped == 40 - len(got) > 0
    assert [r.place for r in got] == list(range(40 - len(got), 40)) and stats.damaged == 0
    on_disk = sum(p.stat().st_size for p in log.glob("*.seg"))
    assert value("hmpf_experience_bytes") == on_disk <= 2**20
    ExperienceLog(log).close()  # released


def _in_sequence(
    answer: LocalizeResponse, off_map: bool = False, status: str = "tracking"
) -> LocalizeResponse:
    """``answer`` as a sequence-mode answer (its report: what the lead-in rule reads)."""
    report = {
        "status": status,
        "match": answer.match.model_dump() if answer.match is not None else None,
        "mass": 0.5,
        "locked": False,
        "off_map": off_map,
        "off_map_probability": 0.9 if off_map else 0.0,
        "frames": 3,
        "track": "t",
    }
    return answer.model_copy(update={"sequence": SequenceReport.model_validate(report)})


def test_the_lead_in_is_recorded_before_the_lock_and_held_within_its_bounds(
    frames: list[Path], tmp_path: Path
) -> None:
    """The recorder on its own: from a track's start, or an off-map answer, a vehicle's last 2
    frames not recorded go into the log as ``lead`` frames just before its next recorded
    frame (those within 30 s before it); a lock lost and found again on the map has none;
    single-mode frames are never a lead; what is held stays within its byte bound (the
    vehicle heard from longest ago goes)."""
    log = tmp_path / "experiences"
    data = frames[0].read_bytes()
    size = len(data) + 1024  # what a held frame counts for; an open vehicle 1024 more
    s = load_settings(
        auth=False,
        experience_log=log,
        experience_min_p_correct=THRESHOLD,
        experience_lead_bytes=3 * size + 2 * 1024,
    )
    m = Metrics()
    rec = Recorder(s, m)
    rec.start()

    def offer(
        p: float, place: int, vehicle: str | None, t: float, off: bool = False, status: str = ""
    ) -> bool:
        answer = _answer(p, p >= THRESHOLD, "sequence", place)
        if vehicle is not None:
            answer = _in_sequence(answer, off, status or "tracking")
        return rec.offer(answer, data, "image/jpeg", vehicle, t, t + 0.5)

    assert not offer(0.5, 1, "car", 100.0, status="started")  # the track starts: open
    assert not offer(0.5, 2, "car", 101.0)
    assert not offer(0.5, 3, "car", 102.0)  # three unsure frames: the last 2 kept
    assert not offer(0.5, 9, None, 102.5)  # single mode: not held
    held = m.registry.get_sample_value("hmpf_experience_lead_bytes")
    assert held == rec.leads.bytes == 2 * size + 1024
    assert offer(0.95, 4, "car", 103.0)  # the lock: its lead-in first
    assert rec.leads.bytes == 0
    assert not offer(0.5, 5, "car", 104.0)  # the lock lost on the map: no lead-in
    assert offer(0.95, 6, "car", 105.0)
    assert not offer(0.5, 7, "car", 106.0, off=True)  # off the map: open again
    assert not offer(0.5, 8, "car", 107.0)
    assert not offer(0.5, 9, "car", 108.0)
    assert offer(0.95, 10, "car", 109.0)  # back on the map: its lead-in
    assert not offer(0.5, 11, "car", 110.0, off=True)
    assert not offer(0.5, 12, "car", 111.0)  # 40 s before the next recorded frame: too old
    assert offer(0.95, 13, "car", 151.0)
    # the byte bound: a 3rd open vehicle pushes out the vehicle heard from longest ago
    assert not offer(0.5, 10, "a", 200.0, status="started")
    assert not offer(0.5, 11, "b", 200.0, status="reset")
    assert not offer(0.5, 12, "b", 201.0)
    assert not offer(0.5, 13, "c", 201.0, status="started")
    assert rec.leads.bytes == 3 * size + 2 * 1024
    assert rec.leads.take(rec_frame("a", 202.0)) == []
    assert [f.place for f in rec.leads.take(rec_frame("b", 202.0))] == [11, 12]
    assert [f.place for f in rec.leads.take(rec_frame("c", 202.0, "v0002"))] == []  # version
    assert rec.leads.bytes == 0
    rec.stop()
    got, _ = _read(log)
    assert [(r.place, r.mode) for r in got] == [
        (2, "lead"),
        (3, "lead"),
        (4, "sequence"),
        (6, "sequence"),
        (8, "lead"),
        (9, "lead"),
        (10, "sequence"),
        (13, "sequence"),
    ]
    assert [r.p_correct for r in got[:2]] == [0.5, 0.5] and got[0].features is None
    assert [r.timestamp for r in got[:3]] == [101.0, 102.0, 103.0]


def test_the_lead_in_never_takes_the_recorded_frames_place(
    frames: list[Path], tmp_path: Path
) -> None:
    """A lead-in goes on the queue only when it and its recorded frame fit (the frame comes
    first); a track's start without a match still opens the vehicle; any recorded frame
    closes it; without sequence records nothing is held."""
    data = frames[0].read_bytes()

    def answer(p: float | None, place: int, status: str = "tracking") -> LocalizeResponse:
        a = _answer(p, p is not None and p >= THRESHOLD, "sequence", place)
        if p is None:
            a = a.model_copy(update={"match": None})
        return _in_sequence(a, status=status)

    s = load_settings(auth=False, experience_log=tmp_path / "a", experience_queue=2)
    m = Metrics()
    rec = Recorder(s, m)  # not started: the queue fills
    assert not rec.offer(answer(None, 0, "started"), data, None, "car", 1.0, 1.0)
    assert not rec.offer(answer(0.5, 1), data, None, "car", 2.0, 2.0)
    assert not rec.offer(answer(0.5, 2), data, None, "car", 3.0, 3.0)
    assert len(rec.leads.take(rec_frame("car", 4.0))) == 2  # opened without a match
    assert not rec.offer(answer(0.5, 1, "started"), data, None, "car", 5.0, 5.0)
    assert not rec.offer(answer(0.5, 2), data, None, "car", 6.0, 6.0)
    assert rec.offer(answer(0.995, 3), data, None, "car", 7.0, 7.0)  # 2 leads + 1 > 2 slots
    dropped = m.registry.get_sample_value("hmpf_experience_dropped_total", {"reason": "queue_full"})
    assert rec._queue.qsize() == 1 and dropped == 2
    # a recorded single-mode answer closes the vehicle too
    both = load_settings(
        auth=False, experience_log=tmp_path / "b", experience_modes="sequence,single"
    )
    rec = Recorder(both, Metrics())
    assert not rec.offer(answer(0.5, 1, "started"), data, None, "car", 1.0, 1.0)
    single = _answer(0.995, True, "single", 2)
    assert rec.offer(_in_sequence(single), data, None, "car", 2.0, 2.0)
    assert rec.leads.bytes == 0 and rec._queue.qsize() == 1  # no lead before a single record
    # recording single answers only: nothing is held
    only = load_settings(auth=False, experience_log=tmp_path / "c", experience_modes="single")
    rec = Recorder(only, Metrics())
    assert not rec.offer(answer(0.5, 1, "started"), data, None, "car", 1.0, 1.0)
    assert rec.leads.bytes == 0


def rec_frame(vehicle: str, t: float, version: str = "v0001") -> Frame:
    """A recorded frame of ``vehicle`` at time ``t`` (what :meth:`Leads.take` reads)."""
    return Frame(b"x", None, 0, "", version, 0.99, vehicle, t, "sequence", t)


def test_features_that_cannot_be_packed_leave_the_frame_recorded_without_them(
    frames: list[Path], tmp_path: Path, index: Path
) -> None:
    """The recorder packs a frame's features on its thread; features it cannot pack (here
    one method's feature missing) cost the frame its features, never the frame or the
    thread."""
    log = tmp_path / "experiences"
    s = load_settings(auth=False, experience_log=log, experience_min_p_correct=THRESHOLD)
    rec = Recorder(s, Metrics())
    rec.start()
    data = frames[0].read_bytes()
    with IndexReader(index) as reader:
        methods = dict(reader.methods)
        feats = reader.extract_query(decode_image(data))
    broken = {k: v for k, v in feats.items() if k != next(iter(methods))}
    answer = _answer(0.95, True, "sequence")
    assert rec.offer(answer, data, "image/jpeg", "car", None, 1.0, broken, methods)
    assert rec.offer(answer, data, "image/jpeg", "car", None, 2.0, feats, methods)
    rec.stop()
    got, _ = _read(log)
    assert [r.features is None for r in got] == [True, False]
    unpacked = unpack_features(methods, got[1].features or b"")
    assert unpacked is not None and unpacked.keys() == feats.keys()


def test_a_sequence_drive_records_its_accepted_answers(
    recording: Server, frames, index: Path
) -> None:
    url, log = recording.url, recording.experiences  # type: ignore[attr-defined]
    car = Car(url, "car-7", frames)
    car.drive(range(0, 20))
    singles = [_single(url, frames[i]) for i in (1, 4, 9)]  # single mode: not enabled
    assert any(b["match"]["accepted"] and b["match"]["p_correct"] >= RECORD_AT for b in singles)
    # A batch in sequence mode: each frame's final answer, stamped when it was received.
    files = [("images", (frames[i].name, frames[i].read_bytes(), "image/jpeg")) for i in (20, 21)]
    before = time.time()
    r = car.http.post(
        "/v1/localize/batch",
        files=files,
        headers={"X-Vehicle-Id": "car-7", "X-Track": car.track or ""},
    )
    assert r.status_code == 200, r.text
    for item, i in zip(r.json()["results"], (20, 21), strict=True):
        car.sent.append((i, item["result"], frames[i].read_bytes(), None))

    recorded = [sent for sent in car.sent if _to_record(sent[1])]
    assert 5 <= len(recorded) < len(car.sent), "some answers recorded, not all"
    expected = _with_leads(car.sent)
    assert any(mode == "lead" for _, mode in expected), "the drive has a lead-in to record"
    m = _wait_recorded(url, len(expected))
    assert m["hmpf_experience_recorded_total"] == len(expected)
    for reason in ("queue_full", "error", "bound"):
        assert _dropped(m, reason) == 0
    got, stats = _read(log)
    assert stats.damaged == 0 and stats.torn == 0
    assert len(got) == len(expected)
    assert m["hmpf_experience_bytes"] == sum(s.stat().st_size for s in log.glob("*.seg"))
    for rec, ((_, body, data, ts), mode) in zip(got, expected, strict=True):
        match = body["match"]
        assert rec.image == data and rec.content_type == "image/jpeg"
        assert (rec.place, rec.place_name) == (match["reference_id"], match["name"])
        assert rec.vehicle == "car-7" and rec.mode == mode
        if mode == "lead":  # its own answer's p_correct (0 without one), no features
            assert rec.p_correct == (match["p_correct"] or 0.0) and rec.features is None
            continue
        assert rec.p_correct == match["p_correct"] >= RECORD_AT
        assert rec.index_version == body["index_version"] == "v0001"
        if ts is None:  # the batch: when it was received
            assert before - 1 <= rec.timestamp <= time.time()
        else:
            assert rec.timestamp == ts
        assert before - 120 <= rec.received <= time.time()
    assert [r.seq for r in got] == list(range(len(got)))
    # Each record carries the features the service answered it with (setting
    # experience_features, on by default), packed for the answering version's methods.
    with IndexReader(index) as reader:
        for rec in [r for r in got if r.mode == "sequence"][:3]:
            assert rec.features is not None
            feats = unpack_features(reader.methods, rec.features)
            assert feats is not None
            again = reader.extract_query(decode_image(rec.image))
            for mid, m in reader.methods.items():
                want, have = m.to_arrays(again[mid]), m.to_arrays(feats[mid])
                assert want.keys() == have.keys()
                for k in want:
                    # The service extracted with its own thread count: a float32 sum may
                    # round to the neighbouring float16 (one step is at most 2**-10 relative).
                    np.testing.assert_allclose(have[k], want[k], rtol=2**-10, atol=1e-5)
    # What the log holds is (nearly always) the right place: frame i shows place i.
    right = sum(abs(rec.place - i) <= 2 for rec, ((i, *_), _) in zip(got, expected, strict=True))
    assert right >= 0.9 * len(got), f"{right}/{len(got)} recorded at the right place"


def test_a_stuck_log_never_holds_up_an_answer(recording: Server, frames) -> None:
    """The log's lock held (as a long prune holds it): the writer waits at its next segment,
    the queue (4 frames) fills, later frames are dropped and counted; every answer comes
    back as fast as ever. Released, the writer goes on and the log is whole."""
    url, log = recording.url, recording.experiences  # type: ignore[attr-defined]
    start = metrics(url)
    car = Car(url, "car-9", frames)
    fd = os.open(log / ".lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        t = time.monotonic()
        car.drive(range(0, 14))
        seconds = time.monotonic() - t
        m = metrics(url)
    finally:
        os.close(fd)
    wanted = len(_with_leads(car.sent))
    assert wanted > 4
    dropped = _dropped(m, "queue_full") - _dropped(start, "queue_full")
    assert dropped >= wanted - 5  # the queue holds 4, the writer 1 in hand
    assert seconds < 14 * 5, "the answers did not wait for the disk"
    end = _settled(url)
    recorded = end["hmpf_experience_recorded_total"] - start["hmpf_experience_recorded_total"]
    assert recorded + dropped == wanted and recorded >= 1
    got, stats = _read(log)
    assert stats.damaged == 0 and sum(r.vehicle == "car-9" for r in got) == recorded


def test_recording_off_records_nothing(index: Path, frames, tmp_path: Path) -> None:
    def files() -> list[str]:  # the sequence key may appear (it does with or without recording)
        return sorted(str(p) for p in index.rglob("*") if p.name != ".sequence-key")

    before = files()
    srv = _server(index, None, tmp_path)
    try:
        car = Car(srv.url, "car-3", frames)
        car.drive(range(0, 8))
        assert any(_to_record(b) for _, b, _, _ in car.sent)
        m = metrics(srv.url)
    finally:
        srv.stop()
    assert m["hmpf_experience_recorded_total"] == 0 and m["hmpf_experience_bytes"] == 0
    assert all(_dropped(m, r) == 0 for r in ("queue_full", "error", "bound"))
    assert files() == before and [p.name for p in tmp_path.iterdir()] == ["serve.log"]
    assert "recording accepted frames" not in srv.output()


def test_a_log_that_cannot_be_created_never_fails_an_answer(
    index: Path, frames, tmp_path: Path
) -> None:
    """The log's folder cannot be made (a file is in the way: refused even to root): the
    service starts and answers, the frames it would record are dropped and counted, and the
    log says why once."""
    (tmp_path / "blocked").write_text("a file, not a folder")
    srv = _server(index, tmp_path / "blocked" / "experiences", tmp_path)
    try:
        car = Car(srv.url, "car-4", frames)
        car.drive(range(0, 8))
        wanted = len(_with_leads(car.sent))
        deadline = time.monotonic() + 20
        while _dropped(m := metrics(srv.url), "error") < wanted and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        srv.stop()
    assert wanted > 0
    assert _dropped(m, "error") == wanted and m["hmpf_experience_recorded_total"] == 0
    out = srv.output()
    assert out.count("cannot be opened; frames are dropped") == 1, out
    assert "Traceback" not in out


def test_kill_9_while_recording_leaves_a_readable_log(recording: Server, frames) -> None:
    """Frames are recorded while the server is killed (SIGKILL) mid-drive: the log reads
    back whole (at most the frame being written is torn), at least every frame the server
    had counted, and a new writer takes the log over and goes on counting."""
    url, log = recording.url, recording.experiences  # type: ignore[attr-defined]
    start = metrics(url)["hmpf_experience_recorded_total"]
    car = Car(url, "car-11", frames)
    stop = threading.Event()

    def drive() -> None:
        try:
            for i in range(0, N_REFS):
                if stop.is_set():
                    return
                car.frame(i)
        except (httpx.HTTPError, AssertionError):
            return  # the server is gone

    t = threading.Thread(target=drive)
    t.start()
    deadline = time.monotonic() + 60
    seen = start
    while seen < start + 4 and time.monotonic() < deadline:
        seen = metrics(url)["hmpf_experience_recorded_total"]
        time.sleep(0.05)
    assert seen >= start + 4, "the drive records"
    recording.proc.send_signal(signal.SIGKILL)
    recording.proc.wait(30)
    stop.set()
    t.join(60)
    got, stats = _read(log)
    assert stats.damaged == 0 and stats.torn <= 1
    assert len(got) >= seen
    assert [r.seq for r in got] == list(range(len(got)))
    with ExperienceLog(log) as w:  # the dead server's hold on the log went with it
        assert w.next_seq == len(got)
