"""Merging fleet experiences into a new index version and removing them by provenance, on a
real index of Gardens Point day_left (30 places) with real day_right / night_right frames:
rows, provenance and manifest of a merge, the dry run, each gate (and all of them open),
frames placed between their time neighbours (against a brute-force reading of the rule),
removal by vehicle / log / time, add and remove of places on a version with experiences
(global and ragged local features, thumbnails), a merge of a real log killed with SIGKILL and
resumed, the Ray extraction path, the parent's FAISS type kept, ``use`` rolling back, and the
config section leaving every preset's digest as it was."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from hmpf.config import ExperienceSettings, load_config, parse_config, preset_names
from hmpf.errors import ConfigError, DatasetError
from hmpf.experience_log import ExperienceLog, Record
from hmpf.features import pack_features, unpack_features
from hmpf.imageio import decode_image, load_image
from hmpf.index import IndexBuildError, IndexReader
from hmpf.sequence import RouteMap
from indexer.build import BuildOptions, add, build, place_count, remove
from indexer.cli import main
from indexer.experiences import (
    _Candidate,
    between_neighbours,
    merge,
    place_leads,
    remove_experiences,
)
from indexer.maintenance import verify, verify_all
from tests.conftest import SMALL_INDEX_CONFIG, write_synthetic_images

N_PLACES = 30
CONFIG = {
    "name": "experiences-test",
    "tiers": [{"methods": ["hog", "gist"], "k": 5}, {"methods": ["gist", "sad"], "k": 1}],
}
OPTS = BuildOptions(workers=1, progress=False)
LOG_A, LOG_B = "a" * 32, "b" * 32
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def gp_map(gardens_point: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An index of the first 30 day_left images (v0001), built once; tests copy it."""
    base = tmp_path_factory.mktemp("exp_map")
    refs = base / "refs"
    refs.mkdir()
    for p in sorted((gardens_point / "day_left").iterdir())[:N_PLACES]:
        (refs / p.name).symlink_to(p)
    build(parse_config(CONFIG), refs, base / "index", options=OPTS)
    return base / "index"


@pytest.fixture
def index(gp_map: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "index"
    shutil.copytree(gp_map, dst, ignore=shutil.ignore_patterns(".lock"))
    return dst


def frame(gardens_point: Path, traverse: str, i: int) -> bytes:
    return (gardens_point / traverse / f"Image{i:03d}.jpg").read_bytes()


def record(
    image: bytes,
    place: int,
    seq: int,
    *,
    log: str = LOG_A,
    vehicle: str = "car1",
    p_correct: float = 0.995,
    timestamp: float = 1.7e9,
    place_name: str | None = None,
    mode: str = "sequence",
) -> Record:
    return Record(
        image=image,
        content_type="image/jpeg",
        place=place,
        place_name=place_name or f"Image{place:03d}.jpg",
        index_version="v0001",
        p_correct=p_correct,
        vehicle=vehicle,
        timestamp=timestamp + seq,
        mode=mode,
        log=log,
        seq=seq,
    )


def localised_place(reader: IndexReader, image: bytes) -> int:
    """Where one frame lands on its own: the service's path (decode, query features)."""
    q = reader.extract_query(decode_image(image))
    return int(reader.hierarchy().run(reader.scorer(q), reader.n).match)


def tree(root: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
    }


def experience_rows(reader: IndexReader) -> range:
    return range(place_count(reader.refs), len(reader.refs))


# -- a merge -------------------------------------------------------------------------------------
def test_dry_run_writes_nothing_then_merge_adds_rows_with_place_and_provenance(
    index: Path, gardens_point: Path
) -> None:
    recs = [record(frame(gardens_point, "day_right", i), i, i) for i in range(0, 12)]
    with IndexReader(index) as r:
        agree = [abs(localised_place(r, rec.image) - rec.place) <= 3 for rec in recs]
    assert sum(agree) >= 8  # day_right frames mostly land near their recorded place
    before = tree(index)
    dry = merge(index, recs, dry_run=True)
    assert tree(index) == before and dry.version is None and dry.dry_run
    assert dry.gates["disagreeing"] == agree.count(False) and dry.added == sum(agree)

    report = merge(index, recs, options=OPTS)
    assert report.version == "v0002" and (index / "CURRENT").read_text().strip() == "v0002"
    assert (report.added, report.records, report.frames_extracted) == (dry.added, 12, 12)
    assert report.gates == dry.gates
    kept = [rec for rec, ok in zip(recs, agree, strict=True) if ok]
    with IndexReader(index) as r:
        refs = r.refs
        assert place_count(refs) == N_PLACES and len(refs) == N_PLACES + len(kept)
        assert np.isnan(refs.meta["place"][:N_PLACES]).all()
        rows = list(experience_rows(r))
        for row, rec in zip(rows, kept, strict=True):
            assert refs.names[row] == f"exp-{LOG_A[:12]}-{rec.seq:06d}.jpg"
            assert refs.sha256[row] == hashlib.sha256(rec.image).hexdigest()
            assert refs.sources[row] == ""
            assert refs.meta["place"][row] == rec.place
            assert refs.meta["exp_log"][row] == LOG_A and refs.meta["exp_vehicle"][row] == "car1"
            assert refs.meta["exp_version"][row] == "v0001"
            assert refs.meta["exp_time"][row] == rec.timestamp
            assert refs.meta["exp_p_correct"][row] == rec.p_correct
            assert r.thumbnail(row) is not None  # a JPEG made from the frame
        # features are the frame's own, as a reference image's would be
        hog = r.methods["hog"].extract(load_image(gardens_point / "day_right" / "Image000.jpg"))
        assert np.allclose(r.global_matrix("hog")[rows[0]], hog)
        assert r.manifest["places"] == {"count": N_PLACES, "experiences": len(kept)}
        entry = r.manifest["experiences"]
        assert entry["logs"] == [LOG_A] and entry["added"] == len(kept)
        assert entry["gates"] == report.gates and entry["settings"]["max_per_place"] == 4
        assert entry["settings"]["agreement_window"] == 3
        assert r.n in (N_PLACES, len(refs))  # places where the reader groups them
    assert verify(index) == []


def test_gates_each_stop_what_they_should(index: Path, gardens_point: Path) -> None:
    day = "day_right"
    recs = [
        record(frame(gardens_point, day, 3), 3, 1),  # kept
        record(frame(gardens_point, day, 3), 3, 2),  # the same frame again: duplicate
        record(frame(gardens_point, "day_left", 4), 4, 3),  # the place's own image: duplicate
        record(frame(gardens_point, day, 6), 6, 4, p_correct=0.5),  # below p_correct
        record(frame(gardens_point, day, 7), 7, 5, place_name="nowhere.jpg"),  # unknown
        record(b"\xff\xd8 not a jpeg", 8, 6),  # unreadable
        record(frame(gardens_point, day, 16), 2, 7),  # injected wrong place: disagreeing
        record(frame(gardens_point, day, 3), 3, 1),  # the input repeats a record
        record(frame(gardens_point, day, 9), 9, 8, p_correct=0.2, mode="lead"),  # unplaced
    ]
    with IndexReader(index) as r:  # the injected frame lands far from its recorded place
        assert abs(localised_place(r, recs[6].image) - 2) > 3
        assert abs(localised_place(r, recs[0].image) - 3) <= 3
    report = merge(index, recs, options=OPTS)
    assert report.gates == {
        "already_merged": 1,
        "below_p_correct": 1,
        "unknown_place": 1,
        "unreadable": 1,
        "unplaced": 1,
        "disagreeing": 1,
        "duplicate": 2,
        "over_cap": 0,
    }
    assert report.added == 1 and report.frames_extracted == 4
    assert any("recorded at Image002.jpg" in line for line in report.rejected_agreement)
    # merging the same log again adds nothing and publishes nothing
    again = merge(index, recs[:1], options=OPTS)
    assert again.version is None and again.gates["already_merged"] == 1
    assert (index / "CURRENT").read_text().strip() == "v0002"
    assert not (index / ".build").exists()
    # a lower confidence threshold given as a flag lets the low one through
    low = merge(index, recs[3:4], settings={"min_p_correct": 0.4}, options=OPTS)
    assert low.added == 1 and low.settings["min_p_correct"] == 0.4
    # every gate open (what the bench compares with): the duplicate of the place's own image
    # and the injected wrong frame go in; what is stored, unknown or unreadable still does not
    opened = merge(index, recs, gates=False, dry_run=True)
    assert opened.settings == ExperienceSettings.open().model_dump()
    assert opened.added == 2 and opened.gates["already_merged"] == 4
    assert opened.gates["unknown_place"] == opened.gates["unreadable"] == 1


def test_cap_keeps_the_frames_that_differ_most(index: Path, gardens_point: Path) -> None:
    """Four frames for one place, room for two (max_per_place 3 with the original): the two
    kept include the one least like the original (greedy farthest point on hog, tier 1's
    first global method); the agreement gate is off to isolate the cap."""
    images = [frame(gardens_point, t, i) for t in ("day_right", "night_right") for i in (10, 11)]
    recs = [record(img, 10, k) for k, img in enumerate(images)]
    settings = {"max_per_place": 3, "agreement_window": -1}
    report = merge(index, recs, settings=settings, options=OPTS)
    assert report.gates["over_cap"] == 2 and report.added == 2
    assert report.settings["agreement_window"] is None
    with IndexReader(index) as r:
        hog = r.methods["hog"]
        original = np.asarray(r.global_matrix("hog")[10], np.float64)
        from hmpf.imageio import decode_image

        vecs = [np.asarray(hog.extract(decode_image(img)), np.float64) for img in images]
        cos = [v @ original / np.linalg.norm(v) / np.linalg.norm(original) for v in vecs]
        farthest = int(np.argmin(cos))
        names = r.refs.names[place_count(r.refs) :]
        assert f"exp-{LOG_A[:12]}-{farthest:06d}.jpg" in names and len(names) == 2
    # the place is full: a further frame is over the cap
    more = merge(index, [record(frame(gardens_point, "night_right", 9), 10, 9)], settings=settings)
    assert more.gates["over_cap"] == 1 and more.version is None


# -- removal, add and remove of places, rollback -----------------------------------------------
def _two_vehicles(index: Path, gardens_point: Path) -> None:
    recs = [record(frame(gardens_point, "day_right", i), i, i) for i in (0, 2, 4, 13)]
    recs += [
        record(frame(gardens_point, "day_right", i), i, i, log=LOG_B, vehicle="car2")
        for i in (1, 3, 14)
    ]
    merge(index, recs, settings={"agreement_window": -1}, options=OPTS)


def _provenance(index: Path) -> list[tuple[str, str, str]]:
    """(name, vehicle, the place's name) of every experience row."""
    with IndexReader(index) as r:
        refs = r.refs
        return [
            (refs.names[i], refs.meta["exp_vehicle"][i], refs.names[int(refs.meta["place"][i])])
            for i in experience_rows(r)
        ]


def test_remove_by_vehicle_log_and_time(index: Path, gardens_point: Path, capsys) -> None:
    _two_vehicles(index, gardens_point)
    assert len(_provenance(index)) == 7
    s = remove_experiences(index, ["vehicle=car2"])
    assert s.version == "v0003" and (s.experiences or {}).get("removed") == 3
    assert {v for _, v, _ in _provenance(index)} == {"car1"}
    with pytest.raises(IndexBuildError, match="no experience of v0003 matches vehicle=car2"):
        remove_experiences(index, ["vehicle=car2"])
    with pytest.raises(DatasetError, match="expected vehicle=V, log=L or before=TIME"):
        remove_experiences(index, ["colour=red"])
    # before: the frames taken before t (car1's seq 0 and 2: timestamps 1.7e9 + seq)
    assert main(["remove", "--index", str(index), "--experiences-from", "before=1700000003"]) == 0
    assert "removed 2 experience(s)" in capsys.readouterr().out
    assert [n for n, _, _ in _provenance(index)] == [
        f"exp-{LOG_A[:12]}-{i:06d}.jpg" for i in (4, 13)
    ]
    s = remove_experiences(index, [f"log={LOG_A}"])
    with IndexReader(index) as r:  # none left: stored as a version that never had any
        assert len(r.refs) == N_PLACES and "place" not in r.refs.meta
        assert "places" not in r.manifest
    assert (index / "CURRENT").read_text().strip() == s.version == "v0005"
    assert main(["remove", "--index", str(index), "--experiences-from", "log=x"]) == 2
    assert "holds no experiences" in capsys.readouterr().err
    assert verify_all(index) == {f"v000{i}": [] for i in range(1, 6)}


def test_add_and_remove_places_keep_experiences_after_places(
    index: Path, gardens_point: Path, tmp_path: Path
) -> None:
    _two_vehicles(index, gardens_point)
    before = _provenance(index)
    with IndexReader(index) as r:
        feats = {r.refs.names[i]: np.array(r.global_matrix("gist")[i]) for i in range(len(r.refs))}
        thumbs = {r.refs.names[i]: r.thumbnail(i) for i in range(len(r.refs))}
    new = tmp_path / "new"
    new.mkdir()
    for i in (30, 31, 32):
        (new / f"Image{i:03d}.jpg").write_bytes(frame(gardens_point, "day_left", i))
    add(index, new, options=OPTS)
    with IndexReader(index) as r:
        refs = r.refs
        assert place_count(refs) == N_PLACES + 3 and len(refs) == N_PLACES + 3 + 7
        assert refs.names[N_PLACES : N_PLACES + 3] == [f"Image{i:03d}.jpg" for i in (30, 31, 32)]
        assert np.isnan(refs.meta["place"][: N_PLACES + 3]).all()
        for i, n in enumerate(refs.names):  # every column and thumbnail moved with its row
            if n in feats:
                assert np.array_equal(r.global_matrix("gist")[i], feats[n]), n
                assert r.thumbnail(i) == thumbs[n], n
        assert r.manifest["places"] == {"count": N_PLACES + 3, "experiences": 7}
    assert _provenance(index) == before  # the experiences' places did not move
    with pytest.raises(IndexBuildError, match="--refit.*fleet experience"):
        add(index, new, options=OPTS, refit=True)
    # removing place Image002 removes its experience and renumbers the later places
    remove(index, ["Image002.jpg"])
    after = _provenance(index)
    assert after == [t for t in before if t[2] != "Image002.jpg"]
    with IndexReader(index) as r:
        assert place_count(r.refs) == N_PLACES + 2 and "Image002.jpg" not in r.refs.names
    # an experience row can be removed by its name too
    remove(index, [after[0][0]])
    assert _provenance(index) == after[1:]
    assert verify(index) == []


def test_info_shows_places_and_use_rolls_back(index: Path, gardens_point: Path, capsys) -> None:
    _two_vehicles(index, gardens_point)
    capsys.readouterr()
    assert main(["info", "--index", str(index)]) == 0
    out = capsys.readouterr().out
    assert "places 30, experiences 7" in out and "added 7" in out
    assert main(["use", "--index", str(index), "v0001"]) == 0
    assert (index / "CURRENT").read_text().strip() == "v0001"
    with IndexReader(index) as r:
        assert len(r.refs) == N_PLACES and "places" not in r.manifest
    assert main(["info", "--index", str(index)]) == 0
    assert "places 30, experiences 0" in capsys.readouterr().out
    assert main(["use", "--index", str(index), "v0002"]) == 0
    with IndexReader(index) as r:
        assert len(r.refs) == N_PLACES + 7


# -- frames placed between their time neighbours ------------------------------------------------
def _cand(place: int, t: float, seq: int, vehicle: str = "car1", log: str = LOG_A) -> _Candidate:
    return _Candidate(log, seq, "0" * 64, place, f"f{seq}.jpg", 0.995, vehicle, "v0001", t)


def _moved(places: list[int], times: list[float], routes: RouteMap) -> list[int]:
    cands = [_cand(p, t, i) for i, (p, t) in enumerate(zip(places, times, strict=True))]
    out, n = between_neighbours(cands, routes)
    assert n == sum(a.place != b.place for a, b in zip(out, cands, strict=True))
    assert [(c.log, c.seq, c.time) for c in out] == [(c.log, c.seq, c.time) for c in cands]
    return [c.place for c in out]


def test_between_neighbours_moves_a_frame_one_place_to_its_neighbours_midpoint() -> None:
    one = RouteMap.from_metadata(20)
    t = [0.0, 1.0, 2.0]
    assert _moved([5, 5, 7], t, one) == [5, 6, 7]  # two frames at one place, the next empty
    assert _moved([5, 7, 7], t, one) == [5, 6, 7]
    assert _moved([7, 7, 5], t, one) == [7, 6, 5]  # driven the other way
    assert _moved([5, 6, 9], t, one) == [5, 7, 9]  # a faster pace: 2 places per step
    assert _moved([5, 6, 7], t, one) == [5, 6, 7]  # already midway
    assert _moved([5, 5, 5], t, one) == [5, 5, 5]  # standing still
    assert _moved([5, 8, 7], t, one) == [5, 8, 7]  # two places off: left as recorded
    assert _moved([5, 5, 6], t, one) == [5, 5, 6]  # neighbours an odd number apart
    assert _moved([5, 5, 7], [0.0, 1.0, 5.0], one) == [5, 5, 7]  # uneven steps
    assert _moved([5, 5, 7], [0.0, 40.0, 80.0], one) == [5, 5, 7]  # too long between
    assert _moved([5, 5, 7], [0.0, float("nan"), 2.0], one) == [5, 5, 7]  # no time
    # a run of frames: each frame is judged by its recorded neighbours, not by moved ones
    # (order-free: the same whichever end is read first)
    assert _moved([1, 1, 3, 3, 5], [0, 1, 2, 3, 4], one) == [1, 2, 2, 4, 5]
    assert _moved([5, 3, 3, 1, 1], [0, 1, 2, 3, 4], one) == [5, 4, 2, 2, 1]
    # the record order breaks a tie in time; the input order does not matter
    cands = [_cand(7, 2.0, 2), _cand(5, 0.0, 0), _cand(5, 1.0, 1)]
    out, n = between_neighbours(cands, one)
    assert n == 1 and [c.place for c in out] == [7, 5, 6]


def test_between_neighbours_keeps_to_one_vehicle_log_and_route() -> None:
    one = RouteMap.from_metadata(20)
    cands = [_cand(5, 0.0, 0), _cand(5, 1.0, 1, vehicle="car2"), _cand(7, 2.0, 2)]
    assert [c.place for c in between_neighbours(cands, one)[0]] == [5, 5, 7]
    cands = [_cand(5, 0.0, 0), _cand(5, 1.0, 1, log=LOG_B), _cand(7, 2.0, 2)]
    assert [c.place for c in between_neighbours(cands, one)[0]] == [5, 5, 7]
    # two routes of 10 places, each in index order: places 9 and 10 are not neighbours
    two = RouteMap.from_metadata(20, sequence=["a"] * 10 + ["b"] * 10)
    assert _moved([8, 8, 10], [0, 1, 2], two) == [8, 8, 10]
    assert _moved([9, 9, 11], [0, 1, 2], two) == [9, 9, 11]
    assert _moved([10, 10, 12], [0, 1, 2], two) == [10, 11, 12]


def _brute_force(places: list[int], times: list[float]) -> list[int]:
    """The rule read literally, on a one-route map in index order."""
    out = list(places)
    for i in range(1, len(places) - 1):
        d1, d2 = times[i] - times[i - 1], times[i + 1] - times[i]
        if min(d1, d2) <= 0 or max(d1, d2) > 30 or abs(d1 - d2) > 0.25 * max(d1, d2):
            continue
        span = places[i + 1] - places[i - 1]
        if span and span % 2 == 0 and abs(places[i] - (places[i - 1] + span // 2)) == 1:
            out[i] = places[i - 1] + span // 2
    return out


def test_between_neighbours_against_brute_force() -> None:
    one = RouteMap.from_metadata(60)
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(3, 12))
        places = (np.cumsum(rng.integers(0, 3, n)) + rng.integers(-1, 2, n) + 5).tolist()
        times = np.cumsum(rng.choice([1.0, 1.0, 1.1, 2.0, 35.0], n)).tolist()
        assert _moved(places, times, one) == _brute_force(places, times)


def test_merge_places_a_frame_between_its_neighbours(index: Path, gardens_point: Path) -> None:
    # day_right frames 4, 5, 6, the middle one recorded a place early (a recorder's jitter)
    recs = [record(frame(gardens_point, "day_right", i), p, i) for i, p in ((4, 4), (5, 4), (6, 6))]
    kept = merge(index, recs, settings={"interpolate_places": False}, dry_run=True)
    assert kept.interpolated == 0 and kept.settings["interpolate_places"] is False
    report = merge(index, recs, options=OPTS)
    assert report.interpolated == 1 and report.added == 3
    with IndexReader(index) as r:
        places = [int(r.refs.meta["place"][row]) for row in experience_rows(r)]
        assert places == [4, 5, 6]
        entry = r.manifest["experiences"]
        assert entry["interpolated"] == 1 and entry["settings"]["interpolate_places"] is True
    # with every gate open the frames are still placed (not a gate), unless asked not to
    opened = merge(index, recs, gates=False, dry_run=True)
    assert opened.settings["interpolate_places"] is True
    off = merge(index, recs, settings={"interpolate_places": False}, gates=False, dry_run=True)
    assert off.settings["interpolate_places"] is False and off.interpolated == 0


# -- a lock's lead-in placed from the frames after it ---------------------------------------------
def _lead(place: int, t: float, seq: int, vehicle: str = "car1") -> _Candidate:
    return dataclasses.replace(_cand(place, t, seq, vehicle), lead=True)


def _leads_placed(
    leads: list[float],
    places: list[int],
    times: list[float],
    routes: RouteMap,
    own: list[int] | None = None,
) -> list[int | None]:
    """Where leads at ``leads`` (times; their own answers at ``own``, else at the place the
    frames after them give, read from the tests' expectations) go, followed by frames at
    ``places`` / ``times``."""
    cands = [_cand(p, t, 10 + i) for i, (p, t) in enumerate(zip(places, times, strict=True))]
    answers = own if own is not None else [_expected(t, places, times) for t in leads]
    cands += [_lead(a, t, i) for i, (a, t) in enumerate(zip(answers, leads, strict=True))]
    out, placed, left = place_leads(cands, routes)
    assert out[: len(places)] == cands[: len(places)]  # the others untouched, in order
    got = {c.seq: c.place for c in out if c.lead}
    assert (placed, left) == (len(got), len(leads) - len(got))
    return [got.get(i) for i in range(len(leads))]


def _expected(lead: float, places: list[int], times: list[float]) -> int:
    """The rule's place, read literally on a one-route map (the first frame after the lead,
    the pace to the last of the first five after it within 30 s of each other), clipped to
    the map: the lead's own answer where the tests need one that agrees."""
    after = [(t, p) for t, p in zip(times, places, strict=True) if t > lead]
    run = after[:1]
    for t, p in after[1:5]:
        if t - run[-1][0] > 30:
            break
        run.append((t, p))
    if len(run) < 2 or run[-1][0] == run[0][0]:
        return 0
    pace = (run[-1][1] - run[0][1]) / (run[-1][0] - run[0][0])
    back = pace * (run[0][0] - lead)
    return max(0, run[0][1] - int(np.sign(back) * np.floor(abs(back) + 0.5)))


def test_place_leads_goes_back_along_the_route_at_the_pace_after_it() -> None:
    one = RouteMap.from_metadata(20)
    t = [10.0, 11.0, 12.0]
    assert _leads_placed([8.0, 9.0], [5, 6, 7], t, one) == [3, 4]
    assert _leads_placed([8.0], [7, 6, 5], t, one) == [9]  # driven the other way
    assert _leads_placed([8.0], [5, 5, 5], t, one) == [5]  # standing still
    assert _leads_placed([9.0], [5, 7, 9], t, one) == [3]  # 2 places a second
    # half a place back rounds away from the first frame (either way along the route)
    assert _leads_placed([9.0, 7.0], [5, 6, 7], [10, 12, 14], one) == [4, 3]
    assert _leads_placed([9.0], [7, 6, 5], [10, 12, 14], one) == [8]
    # the pace from the first to the fifth frame after it (a jittery second frame)
    assert _leads_placed([9.0], [5, 5, 7, 8, 9, 15], [10, 11, 12, 13, 14, 15], one) == [4]
    # ... from the frames that follow each other within 30 s
    assert _leads_placed([9.0], [5, 6, 15], [10, 11, 60], one) == [4]
    # not placed: one frame after it, too long before it, none after it, before the start
    assert _leads_placed([9.0], [5], [10.0], one) == [None]
    assert _leads_placed([9.0], [5, 6], [40.0, 41.0], one) == [None]
    assert _leads_placed([13.0], [5, 6, 7], t, one) == [None]
    assert _leads_placed([6.0], [1, 2, 3], t, one) == [None]
    assert _leads_placed([9.0], [5, 6], [10.0, 10.0], one) == [None]  # no time between
    # two routes of 10 places: back from the second route's start is not the first route
    two = RouteMap.from_metadata(20, sequence=["a"] * 10 + ["b"] * 10)
    assert _leads_placed([8.0], [10, 11, 12], t, two) == [None]
    assert _leads_placed([8.0], [12, 13, 14], t, two) == [10]
    assert _leads_placed([8.0], [8, 10, 11], t, two) == [None]  # the next frames change route
    # the lead's own answer must agree with the pace within a place
    assert _leads_placed([8.0], [5, 6, 7], t, one, own=[4]) == [3]
    assert _leads_placed([8.0], [5, 6, 7], t, one, own=[2]) == [3]
    assert _leads_placed([8.0], [5, 6, 7], t, one, own=[5]) == [None]
    assert _leads_placed([8.0], [5, 6, 7], t, one, own=[1]) == [None]
    assert _leads_placed([8.0], [12, 13, 14], t, two, own=[9]) == [None]  # another route
    # another vehicle's frames, or other leads, never give the pace
    cands = [_lead(0, 8.0, 0), _cand(5, 10.0, 1, "car2"), _cand(6, 11.0, 2, "car2")]
    assert place_leads(cands, one)[1:] == (0, 1)
    cands = [_lead(0, 8.0, 0), _lead(5, 10.0, 1), _lead(6, 11.0, 2), _cand(6, 12.0, 3)]
    assert place_leads(cands, one)[1:] == (0, 3)


def test_between_neighbours_neither_moves_a_lead_nor_reads_it() -> None:
    one = RouteMap.from_metadata(20)
    cands = [_cand(5, 0.0, 0), _lead(5, 1.0, 1), _cand(7, 2.0, 2)]
    assert between_neighbours(cands, one) == (cands, 0)
    cands = [_cand(5, 0.0, 0), _cand(5, 1.0, 1), _lead(9, 1.5, 3), _cand(7, 2.0, 2)]
    out, n = between_neighbours(cands, one)
    assert n == 1 and [c.place for c in out] == [5, 6, 9, 7]


def test_merge_places_lead_frames_from_the_frames_after_them(
    index: Path, gardens_point: Path
) -> None:
    # day_right frames 2, 3 recorded as a lock's lead-in (unsure answers, the first a place
    # off), then 4..7 recorded at their places: the leads go to places 2 and 3
    day = [frame(gardens_point, "day_right", i) for i in range(2, 8)]
    recs = [
        record(day[0], 3, 2, p_correct=0.3, mode="lead"),
        record(day[1], 3, 3, p_correct=0.0, mode="lead"),
    ] + [record(day[i - 2], i, i) for i in range(4, 8)]
    # a lead whose own answer is 2 places from where the pace puts it is left out
    far = [dataclasses.replace(recs[0], place=4, place_name="Image004.jpg"), *recs[1:]]
    assert merge(index, far, dry_run=True).gates["unplaced"] == 1
    off = merge(index, recs, settings={"place_leads": False}, dry_run=True)
    assert off.gates["unplaced"] == 2 and off.added == 4 and off.leads_placed == 0
    # with every gate open they are still placed (no place otherwise), unless asked not to
    opened = merge(index, recs, gates=False, dry_run=True)
    assert opened.settings["place_leads"] is True and opened.leads_placed == 2
    off = merge(index, recs, settings={"place_leads": False}, gates=False, dry_run=True)
    assert off.settings["place_leads"] is False and off.gates["unplaced"] == 2
    report = merge(index, recs, options=OPTS)
    assert report.leads_placed == 2 and report.gates["below_p_correct"] == 0
    assert report.added == 6, report.gates
    with IndexReader(index) as r:
        places = [int(r.refs.meta["place"][row]) for row in experience_rows(r)]
        assert places == [2, 3, 4, 5, 6, 7]
        entry = r.manifest["experiences"]
        assert entry["leads_placed"] == 2 and entry["settings"]["place_leads"] is True


def test_cli_rejects_mixed_options(index: Path, tmp_path: Path, capsys) -> None:
    args = ["add", "--index", str(index), "--images", str(tmp_path), "--dry-run"]
    assert main(args) == 2
    assert "--dry-run: only with --experiences" in capsys.readouterr().err
    assert main(["add", "--index", str(index), "--experiences", str(tmp_path / "nope")]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    assert (
        main(["add", "--index", str(index), "--experiences", str(index), "--max-per-place", "0"])
        == 2
    )
    assert "max_per_place: Input should be greater than or equal to 1" in capsys.readouterr().err
    args = ["add", "--index", str(index), "--images", str(tmp_path), "--no-interpolate-places"]
    assert main(args) == 2
    assert "--no-interpolate-places: only with --experiences" in capsys.readouterr().err
    args = ["add", "--index", str(index), "--images", str(tmp_path), "--no-place-leads"]
    assert main(args) == 2
    assert "--no-place-leads: only with --experiences" in capsys.readouterr().err
    assert main(["remove", "--index", str(index)]) == 2
    assert "give --experiences-from" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # --images and --experiences are exclusive
        main(["add", "--index", str(index), "--images", "a", "--experiences", "b"])


# -- a real log, killed mid-way, resumed --------------------------------------------------------
def test_merge_killed_mid_way_leaves_versions_untouched_and_resumes(
    index: Path, gardens_point: Path, tmp_path: Path
) -> None:
    log = tmp_path / "log"
    with ExperienceLog(log) as w:
        for t in ("day_right", "night_right"):
            for i in range(N_PLACES):
                w.append(
                    frame(gardens_point, t, i),
                    content_type="image/jpeg",
                    place=i,
                    place_name=f"Image{i:03d}.jpg",
                    index_version="v0001",
                    p_correct=0.999,
                    vehicle="car1",
                    timestamp=1.7e9 + i,
                    mode="sequence",
                )
    cmd = [sys.executable, "-m", "indexer.cli", "add", "--index", str(index)]
    cmd += ["--experiences", str(log), "--workers", "1", "--quiet"]
    before = tree(index / "v0001")
    proc = subprocess.Popen(cmd, cwd=REPO)
    features = index / ".build" / "features"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        done = len(list(features.rglob("*.npz"))) if features.exists() else 0
        if done >= 3 * 4 or proc.poll() is not None:  # 3 methods x 4 frames
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the merge finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (index / "CURRENT").read_text().strip() == "v0001"
    assert [p.name for p in index.glob("v*")] == ["v0001"] and tree(index / "v0001") == before
    assert verify_all(index) == {"v0001": []}
    out = subprocess.run([*cmd, "--resume"], cwd=REPO, capture_output=True, text=True, check=True)
    assert "merge: published v0002" in out.stdout
    with IndexReader(index) as r:
        summary = r.manifest["summary"]
        assert summary["resumed"] >= 1
        added = r.manifest["experiences"]["added"]
        assert added >= 20 and len(r.refs) == N_PLACES + added
    # the same log merged into a fresh copy without a kill gives the same version
    clean = tmp_path / "clean"
    shutil.copytree(index, clean, ignore=shutil.ignore_patterns(".lock", "v0002"))
    (clean / "CURRENT").write_text("v0001\n")
    subprocess.run(
        [*cmd[:5], str(clean), *cmd[6:]], cwd=REPO, capture_output=True, text=True, check=True
    )
    got, want = (json.loads((d / "v0002" / "manifest.json").read_text()) for d in (index, clean))
    for name in ("references.h5", "local.h5", "thumbnails.h5"):
        if name in want["files"]:
            assert got["files"][name]["sha256"] == want["files"][name]["sha256"], name


# -- the config section -------------------------------------------------------------------------
#: The bundled presets' digests before the ``experiences:`` section existed: the section must
#: not change any index's identity.
PRESET_DIGESTS = {
    "all-global": "2d1855b423c75ae3d64c10e987d930d707a07c096db4ea77cfdd650c1b60826b",
    "all-methods": "c6b870c0297fa2a0c51e4f646c53573422a2ac09a03d101073e37299b5a08e3b",
    "calibrated/gp_dl_dr": "798524c599707d6cd83fe8ce8aa99673b46446e37e5d083df163291e54b8f050",
    "calibrated/gp_dl_nr": "289a5b82edb911a04dbe6b18777d482aa31d9b2610bdce24d2ed786030ae91c8",
    "calibrated/gp_dr_nr": "83eb88204bed88ca904210bcd57f89de05cf9a1496c305b6484ad239a5e9d63b",
    "calibrated/nordland_handcrafted": (
        "f79ed153e0275a650f30a15100739251f577743962722a04c0cede04c28ee2eb"
    ),
    "calibration-pool": "805914642092a38090018a4226710e0f0483dcac79152a49c758c1b2907f02f4",
    "calibration-pool-extended": "ce32d33117042345c8ad9908f0c515a27d7e2c0bfcb570d791aeb3b2f9910dc8",
    "default": "535bc71b0d274185708ad861c3c25c2b058ac5ebb5882e013cdc9d49ecea65dc",
    "default-lite0": "2d52a6db0f6e8333d7942e15c2dcdf99400895740816a6efbc292346758d1ce3",
    "fast": "37de88e57a28800a1b912db8ffe47462728ecd8f8b9918ef3fff3a5a74775010",
    "handcrafted": "275a6a5d8a7ef6e9b4d868a48b946b8081fd6acb575d604243c04c252a9078e6",
    "handcrafted-faithful": "f3de6ca9f5511923036948b84f125bc6d7dc66aae61e3f494e05b1cc7c4f0227",
    "netvlad-lite1": "e918939c17cef835f9528c1bc2aa27eb37e13e2a4f1103a5903fdcbfedcf8ff0",
    "paper-berlin": "cf5e9a4fbd4bda4d097f7fb602e194ea907b359f6887ac2c0a11312f4f949bb2",
    "paper-nordland": "65aea33e3cfc36aecebddd6b5c52089c0b17345ce5ff4f9dcc866210b44f571e",
    "single-tier": "5249a442f6619689f6443547f6af2aa9a4a057953c8f60f6508aa86b3c719c59",
    "thumbnails": "ba1156c4201ca2f7615ffd21d0a9b449965c20a7886322dbb694b1368998fb9d",
}


def test_experiences_section_leaves_digests_unchanged() -> None:
    assert {n: load_config(n).digest() for n in preset_names()} == PRESET_DIGESTS
    plain = parse_config(CONFIG)
    tuned = parse_config({**CONFIG, "experiences": {"max_per_place": 2, "min_p_correct": 0.9}})
    assert tuned.digest() == plain.digest()
    assert tuned.experience_settings.max_per_place == 2
    assert plain.experience_settings == ExperienceSettings()
    with pytest.raises(ConfigError, match="max_per_place"):
        parse_config({**CONFIG, "experiences": {"max_per_place": 0}})
    with pytest.raises(ConfigError, match="experiences"):
        parse_config({**CONFIG, "experiences": {"max_experiences": 2}})


def test_merge_on_ray_equals_local(index: Path, gardens_point: Path, tmp_path: Path) -> None:
    """The frames' features come from the build's extraction, Ray included: the same bits."""
    pytest.importorskip("ray")
    from indexer.distributed import RayOptions

    recs = [record(frame(gardens_point, "night_right", i), i, i) for i in range(0, 30, 3)]
    local = tmp_path / "local"
    shutil.copytree(index, local, ignore=shutil.ignore_patterns(".lock"))
    merge(local, recs, options=OPTS)
    ray = BuildOptions(workers=1, progress=False, ray=RayOptions(workers=1))
    merge(index, recs, options=ray)
    got, want = (json.loads((d / "v0002" / "manifest.json").read_text()) for d in (index, local))
    assert got["experiences"]["added"] == want["experiences"]["added"] > 0
    for name in ("references.h5", "local.h5", "thumbnails.h5"):
        if name in want["files"]:
            assert got["files"][name]["sha256"] == want["files"][name]["sha256"], name


def test_features_recorded_with_the_frames_are_read_not_extracted(
    index: Path, gardens_point: Path, tmp_path: Path
) -> None:
    """Frames whose records carry the features the service answered them with (packed by the
    version's own methods) merge without extraction, to the same gates, rows and features as
    extracting them; features packed by other methods, or not laid out as the version's rows
    (bytes crafted to the right keys: a wrong size, values that are not finite), are not
    trusted: those are extracted."""
    plain = [record(frame(gardens_point, "day_right", i), i, i) for i in range(12)]
    with IndexReader(index) as r:
        query = [r.extract_query(decode_image(rec.image)) for rec in plain]
        packed = [pack_features(r.methods, q) for q in query]
        hog_only = pack_features({"hog": r.methods["hog"]}, query[0])
        short = pack_features(r.methods, {**query[1], "gist": query[1]["gist"][:10]})
        nan = np.full_like(query[2]["hog"], np.nan)
        not_finite = pack_features(r.methods, {**query[2], "hog": nan})
    assert unpack_features(dict(r.methods), b"not an npz") is None
    rich = [dataclasses.replace(rec, features=f) for rec, f in zip(plain, packed, strict=True)]
    rich[0] = dataclasses.replace(rich[0], features=hog_only)
    rich[1] = dataclasses.replace(rich[1], features=short)
    rich[2] = dataclasses.replace(rich[2], features=not_finite)
    other = tmp_path / "other"
    shutil.copytree(index, other, ignore=shutil.ignore_patterns(".lock"))
    extracted, read = merge(index, plain, options=OPTS), merge(other, rich, options=OPTS)
    assert (extracted.frames_extracted, extracted.features_recorded) == (12, 0)
    assert (read.frames_extracted, read.features_recorded) == (3, 9)
    assert read.gates == extracted.gates and read.added == extracted.added > 0
    manifest = json.loads((other / "v0002" / "manifest.json").read_text())
    assert manifest["experiences"]["features_recorded"] == 9
    with IndexReader(index) as a, IndexReader(other) as b:
        assert a.refs.names == b.refs.names
        for mid in a.methods:  # the service's decode and extraction equal the build's here
            np.testing.assert_allclose(
                np.asarray(b.columns(mid)), np.asarray(a.columns(mid)), rtol=0, atol=1e-6
            )


def test_derived_versions_keep_the_parents_faiss_type(index: Path, gardens_point: Path) -> None:
    """A merge and a plain remove store tier 1 as the parent did (here IVF), not as Flat; the
    merge takes its knobs from the config's ``experiences:`` section."""
    with IndexReader(index) as r:
        refs = sorted({Path(s) / n for s, n in zip(r.refs.sources, r.refs.names, strict=True)})
    ivf, folder = index.parent / "ivf", index.parent / "ivf_refs"
    folder.mkdir()
    for p in refs:
        (folder / p.name).symlink_to(p)
    opts = BuildOptions(workers=1, progress=False, faiss={"*": "IVF2,Flat"})
    build(
        parse_config({**CONFIG, "experiences": {"agreement_window": 7}}), folder, ivf, options=opts
    )
    report = merge(ivf, [record(frame(gardens_point, "day_right", 5), 5, 1)], options=OPTS)
    assert report.settings["agreement_window"] == 7  # the config's own section
    remove(ivf, ["Image000.jpg"])
    for version in ("v0002", "v0003"):
        with IndexReader(ivf, version) as r:
            assert r.faiss_info("gist")["factory"] == "IVF2,Flat", version  # type: ignore[index]


def test_local_features_move_with_their_rows(tmp_path: Path) -> None:
    """Ragged local arrays (KAZE keypoints) stay with their row when add inserts places
    before the experiences and remove drops a place with its experience (synthetic images,
    a hierarchy with a local method)."""
    refs = write_synthetic_images(tmp_path / "refs", 6)
    index = tmp_path / "index"
    build(parse_config(yaml.safe_load(SMALL_INDEX_CONFIG)), refs, index, options=OPTS)
    frames = write_synthetic_images(tmp_path / "frames", 3, seed=100, prefix="f")
    recs = [
        record((frames / f"f{k:03d}.png").read_bytes(), p, k, place_name=f"img{p:03d}.png")
        for k, p in enumerate((1, 2, 4))
    ]
    assert merge(index, recs, settings={"agreement_window": -1}, options=OPTS).added == 3

    def kaze_by_name(version: str) -> dict[str, dict[str, np.ndarray]]:
        with IndexReader(index, version) as r:
            feats = r.local_features("kaze", np.arange(len(r.refs)))
            return {
                n: r.methods["kaze"].to_arrays(f) for n, f in zip(r.refs.names, feats, strict=True)
            }

    merged = kaze_by_name("v0002")
    add(index, write_synthetic_images(tmp_path / "new", 2, seed=50, prefix="new"), options=OPTS)
    remove(index, ["img002.png"])
    for version, gone in (
        ("v0003", set()),
        ("v0004", {"img002.png", "exp-aaaaaaaaaaaa-000001.png"}),
    ):
        now = kaze_by_name(version)
        assert set(merged) - set(now) == gone
        for name, arrays in now.items():
            if name in merged:
                for key, value in arrays.items():
                    assert np.array_equal(value, merged[name][key]), (version, name, key)
    with IndexReader(index) as r:
        names = r.refs.names
        assert names[: place_count(r.refs)] == [f"img{i:03d}.png" for i in (0, 1, 3, 4, 5)] + [
            "new000.png",
            "new001.png",
        ]
        places = r.refs.meta["place"][place_count(r.refs) :]
        assert [names[int(p)] for p in places] == ["img001.png", "img004.png"]
