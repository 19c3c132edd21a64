"""Sequence mode's arithmetic cannot be made to fail by a client (issue 36, item 2).

Timestamps 0 -> 5e-324 -> 1 once made the learned frame interval denormal, and the next
frame's ``round(dt / interval)`` raised ``OverflowError``: a 500 with a traceback, and the
token, which carried that interval, made every later frame of the vehicle a 500 too.
:func:`service.track.frame_steps` now answers for any input; :func:`service.track.follow`
runs over any finite timestamps; the service's edge refuses a timestamp outside
:data:`service.schemas.MAX_TIMESTAMP_S`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st

from service.app import create_app
from service.settings import load_settings
from service.track import TokenCodec, frame_steps, load_or_create_key
from tests.service.hardening_helpers import assert_json_below_500, sequence_request, track_of

#: Any float, the awkward ones included.
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True)


def test_a_denormal_interval_does_not_overflow() -> None:
    steps, interval = frame_steps(5e-324, math.nan)  # the second frame of 0 -> 5e-324 -> 1
    steps, interval = frame_steps(1.0 - 5e-324, interval)  # raised OverflowError
    assert steps == 1 and interval == 1.0  # an interval that small is not a camera's: restart
    for tiny in (5e-324, sys.float_info.min, 1e-300):
        steps, _ = frame_steps(1.0, tiny)
        assert 0 <= steps <= 10_000
    assert frame_steps(sys.float_info.max, 1e-3)[0] == 10_000  # capped, not an overflow


@settings(max_examples=400, deadline=None, database=None)
@given(dt=ANY_FLOAT, interval=ANY_FLOAT)
def test_frame_steps_answers_for_any_input(dt: float, interval: float) -> None:
    steps, new = frame_steps(dt, interval)
    assert isinstance(steps, int) and 0 <= steps <= 10_000
    # the interval carried on is unknown (NaN) or a usable positive finite number
    assert math.isnan(new) or (math.isfinite(new) and new > 0), new
    if math.isfinite(dt) and dt > 0 and math.isfinite(interval) and interval > 0:
        frame_steps(dt, new)  # and the next frame's step with it is fine too


# -- through the real app ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def client(service_index: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    key_file = tmp_path_factory.mktemp("hardening-track") / "sequence.key"
    settings = load_settings(
        None, index=service_index, auth=False, workers=1, queue=4, sequence_key_file=key_file
    )
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="module")
def frame(gardens_point: Path) -> bytes:
    return sorted((gardens_point / "night_right").iterdir())[3].read_bytes()


def _drive(client: TestClient, frame: bytes, vehicle: str, stamps: list[Any]) -> list[Any]:
    document = client.app.openapi()  # type: ignore[attr-defined]
    track, out = None, []
    for ts in stamps:
        params, headers = sequence_request(document, vehicle, track, ts)
        r = client.post(
            "/v1/localize",
            params=params,
            headers=headers,
            files={"image": ("f.jpg", frame, "image/jpeg")},
        )
        assert_json_below_500(r, f"timestamps {stamps}")
        track = track_of(r) or track
        out.append(r)
    return out


def test_denormal_timestamps_are_answered_and_the_track_goes_on(
    client: TestClient, frame: bytes
) -> None:
    answers = _drive(client, frame, "car-denormal", [0.0, 5e-324, 1.0, 2.0, 3.0])
    assert [r.status_code for r in answers] == [200] * 5, [r.text for r in answers]
    assert answers[-1].json()["sequence"]["status"] == "tracking"


def test_timestamps_out_of_range_are_a_json_422(client: TestClient, frame: bytes) -> None:
    for bad in ("1e300", "-1e300", "1.7976931348623157e308", "inf", "nan", "1e13"):
        (r,) = _drive(client, frame, "car-range", [bad])
        assert r.status_code == 422, (bad, r.text)
        assert "timestamp" in r.json()["error"]["message"], r.text
    (r,) = _drive(client, frame, "car-range", [1.7e9])  # an epoch in seconds, as documented
    assert r.status_code == 200, r.text


@pytest.mark.parametrize(
    "odd",
    [
        {"interval": 5e-324},
        {"interval": -1.0},
        {"interval": math.inf},
        {"interval": 1e308},
        {"timestamp": -1e308},
        {"timestamp": math.inf},
        {"issued_at": math.nan},
    ],
    ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()),
)
def test_a_signed_track_with_odd_numbers_never_makes_a_500(
    client: TestClient, frame: bytes, odd: dict[str, float]
) -> None:
    """A token signed by the service whose numbers are odd (as an older service's arithmetic
    could have left them) continues or restarts the track: 200 or a JSON 422, never a 500,
    and the vehicle's next frame is answered."""
    settings = client.app.state.settings  # type: ignore[attr-defined]
    codec = TokenCodec(load_or_create_key(settings.sequence_key_file))
    (first,) = _drive(client, frame, "car-odd", [10.0])
    track = codec.decode(track_of(first) or "", "car-odd")
    poisoned = codec.encode(dataclasses.replace(track, **odd))
    document = client.app.openapi()  # type: ignore[attr-defined]
    token: str | None = poisoned
    for ts in (11.0, 12.0, 13.0):
        params, headers = sequence_request(document, "car-odd", token, ts)
        r = client.post(
            "/v1/localize", params=params, headers=headers,
            files={"image": ("f.jpg", frame, "image/jpeg")},
        )  # fmt: skip
        assert_json_below_500(r, str(odd))
        token = track_of(r)  # None after a 422: the vehicle starts a new track
    assert r.status_code == 200, r.text


def test_no_sequence_key_is_a_503_without_a_path_and_with_retry_after(
    service_index: Path,
    tmp_path: Path,
    frame: bytes,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The key file cannot be created (its folder is missing): the vehicle hears a 503 with
    Retry-After that names no server path; the operator finds the path in the log."""
    key_file = tmp_path / "missing-folder" / "sequence.key"
    settings = load_settings(
        None, index=service_index, auth=False, workers=1, queue=4, sequence_key_file=key_file
    )
    with TestClient(create_app(settings)) as c, caplog.at_level("ERROR", "hmpf.service"):
        document = c.app.openapi()  # type: ignore[attr-defined]
        params, headers = sequence_request(document, "car-nokey", None, 1.0)
        r = c.post(
            "/v1/localize", params=params, headers=headers,
            files={"image": ("f.jpg", frame, "image/jpeg")},
        )  # fmt: skip
    assert r.status_code == 503, r.text
    error = r.json()["error"]
    assert error["code"] == "sequence_unavailable"
    assert "HMPF_SEQUENCE_KEY" in error["message"]  # what the operator sets
    for leak in (str(tmp_path), "missing-folder", "sequence.key", str(service_index), "/"):
        assert leak not in error["message"], error["message"]
    assert int(r.headers["Retry-After"]) > 0
    assert str(key_file) in caplog.text  # the path is in the service's log
