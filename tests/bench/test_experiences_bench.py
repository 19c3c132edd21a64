"""bench.experiences' own steps on a small real index: a log of frames at their true places
(what the ``scenarios`` and ``cost`` runs merge), merged by the real ``hmpf-index add`` with
the gates open, audited against the ground truth."""

from __future__ import annotations

import shutil
from pathlib import Path

from bench.experiences import merge, merged_rows, truth_log, truth_of
from hmpf.experience_log import read_log
from hmpf.index.reader import IndexReader


def test_truth_log_merges_every_frame_at_its_place(
    service_index: Path, gardens_point: Path, tmp_path: Path
) -> None:
    index = tmp_path / "index"
    shutil.copytree(service_index, index)
    frames = sorted((gardens_point / "night_right").iterdir())[:6]
    places = [0, 1, 2, 3, 4, 5]
    log = truth_log(index, tmp_path / "night.log", frames, places)
    records = list(read_log(log))
    with IndexReader(index) as reader:
        names = reader.place_names
    assert [r.place for r in records] == places
    assert [r.place_name for r in records] == names[:6]
    assert {r.vehicle for r in records} == {"truth-night"}
    assert [r.image for r in records] == [p.read_bytes() for p in frames]

    done = merge(index, [log], "--no-gates")
    assert done["places"] == {"count": 20, "experiences": 6}
    assert merged_rows(index, truth_of(frames)) == {"experiences": 6, "wrong": 0}
    # the audit counts a frame merged 3 places away as wrong
    shifted = {k: v + 3 for k, v in truth_of(frames).items()}
    assert merged_rows(index, shifted) == {"experiences": 6, "wrong": 6}


def test_merge_places_a_jittered_frame_between_its_neighbours(
    service_index: Path, gardens_point: Path, tmp_path: Path
) -> None:
    """A log whose second frame was recorded a place early (a recorder's jitter): the merge
    places it between its time neighbours unless told not to (the bench's ``as_recorded``)."""
    frames = sorted((gardens_point / "night_right").iterdir())[:6]
    places = [0, 0, 2, 3, 4, 5]
    for extra, moved, where in (((), 1, 1), (("--no-interpolate-places",), 0, 0)):
        index = tmp_path / f"index{moved}"
        shutil.copytree(service_index, index)
        log = truth_log(index, tmp_path / f"jitter{moved}.log", frames, places)
        done = merge(index, [log], "--no-gates", *extra)
        assert done["report"]["interpolated"] == moved
        with IndexReader(index) as reader:
            rows = range(reader.places.n, reader.places.n_rows)
            got = [int(reader.places.place_of[r]) for r in rows]
        assert got == [0, where, 2, 3, 4, 5]
