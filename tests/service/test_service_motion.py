"""The sequence filter's motion cue (``sequence: {stop_factor: ...}``) in the service, on a
real index (Gardens Point day_right, 20 references) and real night frames; no mocks.

A version built with the cue: the service sketches each frame (tier 1's first global
method) and carries the sketch in the track token; ``hmpf-eval --index`` runs the same
filter with the same sketches, so it gives the service's sequence answers frame by frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from hmpf.config import parse_config
from hmpf.index.reader import IndexReader
from hmpf.sequence import SKETCH_DIM
from indexer.build import build
from service.app import create_app
from service.auth import add_key
from service.settings import load_settings
from tests.conftest import SERVICE_CONFIG
from tests.service_helpers import BUILD_OPTIONS, evaluate_frames

TOLERANCE = 2
FRAMES = range(0, 14)


@pytest.fixture(scope="module")
def night(gardens_point: Path) -> list[Path]:
    return sorted((gardens_point / "night_right").iterdir())


@pytest.fixture(scope="module")
def motion_index(service_index: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = dict(SERVICE_CONFIG, sequence={"lock_mass": 0.9, "stop_factor": 0.1})
    root = tmp_path_factory.mktemp("motion") / "index"
    base = service_index.parent
    build(
        parse_config(config), base / "refs", root, metadata=base / "meta.csv",
        options=BUILD_OPTIONS,
    )  # fmt: skip
    return root


@pytest.fixture(scope="module")
def keys(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    path = tmp_path_factory.mktemp("motion-keys") / "keys.yaml"
    return {"file": str(path), "vehicle": add_key(path, "car", "vehicle")}


def _client(index: Path, keys: dict[str, str]) -> TestClient:
    settings = load_settings(None, index=index, keys_file=keys["file"], workers=1, queue=4)
    return TestClient(create_app(settings))


def _drive(c: TestClient, keys: dict[str, str], frames: list[Path]) -> list[dict[str, Any]]:
    """The frames as one vehicle's drive, one frame a second; each answer's sequence part."""
    track, out = None, []
    for i, f in enumerate(frames):
        data = {"vehicle_id": "car-motion", "timestamp": str(float(i))}
        if track is not None:
            data["track"] = track
        r = c.post(
            "/v1/localize",
            files={"image": (f.name, f.read_bytes(), "image/jpeg")},
            data=data,
            headers={"X-API-Key": keys["vehicle"]},
        )
        assert r.status_code == 200, r.text
        out.append(r.json()["sequence"])
        track = out[-1]["track"]
    return out


def test_the_version_sketches_on_its_first_global_tier1_method(motion_index: Path) -> None:
    reader = IndexReader(motion_index)
    try:
        motion = reader.motion_sketch()
        assert motion is not None and motion[0] == "hog"
        assert motion[1].projection.shape[0] == SKETCH_DIM and motion[1].step > 0
    finally:
        reader.close()


def test_hmpf_eval_on_the_index_gives_the_services_sequence_answers(
    motion_index: Path, service_index: Path, keys: dict[str, str], night: list[Path]
) -> None:
    """The service and hmpf-eval --index run the filter with the same sketches: the same
    estimates, right or wrong, and masses equal up to the token's float16 logs. The token
    carries the sketch: it is longer than a version without the cue's by the sketch's bytes."""
    frames = [night[i] for i in FRAMES]
    rep = evaluate_frames(motion_index, frames, list(FRAMES), TOLERANCE)
    assert rep["sequence"]["params"]["stop_factor"] == 0.1
    with _client(motion_index, keys) as c:
        served = _drive(c, keys, frames)
    right = [
        abs(s["match"]["reference_id"] - i) <= TOLERANCE
        for s, i in zip(served, FRAMES, strict=True)
    ]
    assert rep["sequence"]["full_drive"]["correct"] == [int(x) for x in right]
    # The token keeps the 64 most probable hypotheses (the rest joins the even background,
    # whose stopped share the cue weighs on average) as float16 logs: masses agree to ~1e-2
    # (measured: 0.013 at most, on the second frame, where the belief is widest).
    assert rep["sequence"]["full_drive"]["mass"] == pytest.approx(
        [s["mass"] for s in served], abs=0.025
    )
    with _client(service_index, keys) as c:
        plain = _drive(c, keys, frames)
    # base64 of 2 x SKETCH_DIM more bytes (4 characters per 3 bytes, give or take padding)
    extra = len(served[-1]["track"]) - len(plain[-1]["track"])
    assert abs(extra - 4 * 2 * SKETCH_DIM / 3) <= 3, extra


@pytest.fixture(scope="module")
def client(motion_index: Path, keys: dict[str, str]) -> Iterator[TestClient]:
    with _client(motion_index, keys) as c:
        yield c


def test_a_track_restarted_mid_drive_keeps_answering(client: TestClient, keys, night) -> None:
    """Without a token (a new track) the first frame has no previous sketch: answered as
    before, and the next frame weighs its motion."""
    frames = [night[i] for i in range(30, 34)]
    served = _drive(client, keys, frames)
    assert [s["frames"] for s in served] == [1, 2, 3, 4]


def test_a_map_that_cannot_sketch_is_refused_for_a_filter_that_weighs_motion() -> None:
    """A reader of another shape (a sharded map's view has no motion_sketch) under a config
    whose filter weighs motion: refused when loaded (start exits 2, a reload is a 409),
    rather than answering otherwise than the unsharded version would."""
    from types import SimpleNamespace

    from hmpf.errors import ConfigError
    from service.engine import Loaded

    closed = []
    config = parse_config(dict(SERVICE_CONFIG, sequence={"stop_factor": 0.1}))
    view = SimpleNamespace(config=config, path="shards", close=lambda: closed.append(True))
    with pytest.raises(ConfigError, match="stop_factor 0.1"):
        Loaded.over(view, None)
    assert closed == [True]
