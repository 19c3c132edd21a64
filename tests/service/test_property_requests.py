"""Property-based hardening (Hypothesis): every numeric input of the API, generated, against the
real app over a real index; no answer is a 500, every error is the project's JSON.

The app is the real one (:func:`service.app.create_app`) over the session's small real index
(``service_index``: 20 Gardens Point references with positions), asked through Starlette's
TestClient with ``raise_server_exceptions=False``, so a request that breaks the server is
seen as a client sees it (a 500). Generated values are sent as text, as HTTP carries them:
any float's ``repr`` (NaN, infinities, subnormals, the largest), integers far beyond 64
bits, and spellings that fool parsers (``²`` passes ``str.isdigit``, ``١٢`` is read by
``int``, 5,000 digits are refused by ``int``, ``1e400`` overflows ``float``). They go to:

* ``lat``, ``lon``, ``radius_m``, ``top_k``, ``timestamp`` of ``/v1/localize`` (query or
  form, one vehicle in sequence mode or none) and of ``/v1/localize/batch``;
* a vehicle's sequence of ``timestamp`` values, frame after frame with its track;
* the reference id of ``/v1/references/{reference}/thumbnail`` and ``/v1/evidence``.

Seeded and bounded (``derandomize``, no example database): about 300 requests, 10-20 s on two
cores.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import cv2
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.app import create_app
from service.settings import load_settings
from tests.service.hardening_helpers import assert_json_below_500, sequence_request, track_of

#: One Hypothesis setting for every property here: seeded, bounded, no example database.
PROPERTY = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
#: Spellings of numbers that parsers disagree about.
ODD_NUMBERS = [
    "²",
    "١٢",
    "0x10",
    "1_000",
    " 1",
    "",
    "1e400",
    "-1e400",
    "nan",
    "-inf",
    "Infinity",
    "5e-324",
    "-0",
    "9" * 5000,
    "-" + "9" * 400,
    "1" + "0" * 4300,
]
#: Any number as HTTP carries it: a float's repr, a huge integer, or an odd spelling.
NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True).map(repr),
    st.integers(min_value=-(10**40), max_value=10**40).map(str),
    st.sampled_from(ODD_NUMBERS),
)
FIELDS = ("lat", "lon", "radius_m", "top_k", "timestamp")
#: Answers seen, per property and status (and sequence status): checked when the module ends,
#: so that the properties are known to have reached what they test (answers, the filter).
SEEN: Counter[tuple[str, str]] = Counter()


def _seen(what: str, r: Any) -> None:
    SEEN[what, str(r.status_code)] += 1
    if r.status_code == 200 and "sequence" in r.json() and r.json()["sequence"]:
        SEEN[what, r.json()["sequence"]["status"]] += 1


@pytest.fixture(scope="module")
def client(service_index: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    key_file = tmp_path_factory.mktemp("property") / "sequence.key"
    config = load_settings(
        None,
        index=service_index,
        auth=False,
        workers=1,
        queue=8,
        max_top_k=10,
        max_batch=3,
        sequence_key_file=key_file,
    )
    with TestClient(create_app(config), raise_server_exceptions=False) as c:
        yield c
    if SEEN:  # the properties ran (not deselected): they reached what they are about
        assert SEEN["fields", "200"] and SEEN["fields", "422"], SEEN
        assert SEEN["batch", "200"] and SEEN["batch", "422"], SEEN
        assert SEEN["stamps", "tracking"] and SEEN["stamps", "422"], SEEN
        assert SEEN["reference", "200"] or SEEN["reference", "404"], SEEN


@pytest.fixture(scope="module")
def frame(gardens_point: Path) -> bytes:
    """A real night frame of the indexed stretch, small (160 x 120 JPEG): quick to answer."""
    path = sorted((gardens_point / "night_right").iterdir())[5]
    image = cv2.resize(cv2.imread(str(path)), (160, 120), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 70])
    assert ok
    return buf.tobytes()


def _document(client: TestClient) -> dict[str, Any]:
    return client.app.openapi()  # type: ignore[attr-defined,no-any-return]


# -- the reference ids (issue 36, item 3) ---------------------------------------------------------
@pytest.mark.parametrize("reference", ["²", "١٢", "9" * 5000, "1" + "0" * 4300, "-1", "20"])
def test_a_reference_id_that_is_no_row_is_a_json_4xx(
    client: TestClient, frame: bytes, reference: str
) -> None:
    """``²`` passes ``str.isdigit`` but not ``int``; 4,301 digits pass neither ``int``'s limit;
    ``١٢`` is a number to ``int`` but not a row id; 20 is one past the last row."""
    r = client.get(f"/v1/references/{reference}/thumbnail")
    assert_json_below_500(r, reference[:20])
    assert r.status_code in (404, 422), r.text
    r = client.post(
        "/v1/evidence",
        params={"reference": reference},
        files={"image": ("f.jpg", frame, "image/jpeg")},
    )
    assert_json_below_500(r, reference[:20])
    assert r.status_code in (404, 422), r.text


def test_a_row_id_and_a_name_are_references(client: TestClient) -> None:
    names = client.get("/v1/references").json()["names"]
    for ref in ("0", "19", names[3]):
        r = client.get(f"/v1/references/{ref}/thumbnail")
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg", r.text


@PROPERTY
@given(reference=st.one_of(NUMBER, st.text(max_size=40)))
def test_reference_ids_never_make_a_500(client: TestClient, frame: bytes, reference: str) -> None:
    path = quote(reference, safe="") or "x"  # percent-encoded, as a client sends it
    r = client.get(f"/v1/references/{path}/thumbnail")
    assert_json_below_500(r, f"thumbnail {reference[:40]!r}")
    r = client.post(
        "/v1/evidence",
        params={"reference": reference},
        files={"image": ("f.jpg", frame, "image/jpeg")},
    )
    assert_json_below_500(r, f"evidence {reference[:40]!r}")
    _seen("reference", r)


# -- the localisation fields ----------------------------------------------------------------------
@PROPERTY
@given(
    values=st.fixed_dictionaries({}, optional={name: NUMBER for name in FIELDS}),
    vehicle=st.booleans(),
    form=st.booleans(),
)
def test_localize_numeric_fields_never_make_a_500(
    client: TestClient, frame: bytes, values: dict[str, str], vehicle: bool, form: bool
) -> None:
    params, headers = (
        sequence_request(_document(client), "car-fields", None) if vehicle else ({}, {})
    )
    data = dict(values) if form else {}
    params.update({} if form else values)
    r = client.post(
        "/v1/localize",
        params=params,
        headers=headers,
        data=data,
        files={"image": ("f.jpg", frame, "image/jpeg")},
    )
    assert_json_below_500(r, f"{values} form={form} vehicle={vehicle}")
    _seen("fields", r)


@PROPERTY
@given(values=st.fixed_dictionaries({}, optional={name: NUMBER for name in FIELDS}))
def test_batch_numeric_fields_never_make_a_500(
    client: TestClient, frame: bytes, values: dict[str, str]
) -> None:
    r = client.post(
        "/v1/localize/batch",
        params=values,
        files=[("images", ("a.jpg", frame, "image/jpeg"))] * 2,
    )
    assert_json_below_500(r, str(values))
    _seen("batch", r)


@PROPERTY
@given(stamps=st.lists(NUMBER, min_size=2, max_size=5))
def test_a_vehicles_timestamps_never_make_a_500(
    client: TestClient, frame: bytes, stamps: list[str]
) -> None:
    """Frame after frame, each with the previous answer's track (kept over a refused frame, as
    a client keeps it): every answer below 500, whatever the timestamps."""
    document, track = _document(client), None
    for ts in stamps:
        params, headers = sequence_request(document, "car-stamps", track, ts)
        r = client.post(
            "/v1/localize",
            params=params,
            headers=headers,
            files={"image": ("f.jpg", frame, "image/jpeg")},
        )
        assert_json_below_500(r, f"timestamps {[s[:30] for s in stamps]}")
        _seen("stamps", r)
        track = track_of(r) or track
    # and the vehicle is answered after them
    params, headers = sequence_request(document, "car-stamps", track, None)
    r = client.post(
        "/v1/localize", params=params, headers=headers,
        files={"image": ("f.jpg", frame, "image/jpeg")},
    )  # fmt: skip
    assert_json_below_500(r, "after the timestamps")
