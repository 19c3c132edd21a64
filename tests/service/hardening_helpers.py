"""Helpers of the hardening tests (issue 36): the real app over a real index, asked as a
hostile client would.

:func:`sequence_request` puts a frame's sequence-mode fields (``vehicle_id``, ``track``,
``timestamp``) where the served API takes them, read from the app's own OpenAPI document (a
field is a query parameter, or a header whose name holds the field's word), so these tests
follow the API wherever those fields live.
"""

from __future__ import annotations

from typing import Any

import httpx

__all__ = ["assert_json_below_500", "sequence_request"]


def _where(document: dict[str, Any], word: str) -> tuple[str, str]:
    """("query" | "header", name) of the ``/v1/localize`` parameter named after ``word``."""
    params = document["paths"]["/v1/localize"]["post"].get("parameters", [])
    for p in params:
        if p["name"] == word:
            return p["in"], p["name"]
    for p in params:
        if p["in"] == "header" and word.split("_")[0] in p["name"].lower().replace("-", "_"):
            return "header", p["name"]
    return "query", word


def sequence_request(
    document: dict[str, Any],
    vehicle_id: str,
    track: str | None,
    timestamp: Any = None,
    **query: Any,
) -> tuple[dict[str, str], dict[str, str]]:
    """(query parameters, headers) of one sequence-mode frame."""
    params = {k: str(v) for k, v in query.items() if v is not None}
    headers: dict[str, str] = {}
    for word, value in (("vehicle_id", vehicle_id), ("track", track)):
        if value is None:
            continue
        where, name = _where(document, word)
        (params if where == "query" else headers)[name] = value
    if timestamp is not None:
        params["timestamp"] = timestamp if isinstance(timestamp, str) else repr(timestamp)
    return params, headers


def track_of(r: httpx.Response) -> str | None:
    """The track token an answer hands back (body ``sequence.track``, else a header)."""
    if r.status_code == 200:
        body = r.json()
        seq = body.get("sequence") or {}
        if seq.get("track"):
            return str(seq["track"])
    for name, value in r.headers.items():
        if "track" in name.lower():
            return value
    return None


def assert_json_below_500(r: httpx.Response, what: str = "") -> None:
    """Below 500, and JSON (an error: the project's ``{"error": {code, message}}``)."""
    assert r.status_code < 500, f"{what}: {r.status_code} {r.text[:500]}"
    if r.status_code >= 400:
        assert r.headers.get("content-type", "").startswith("application/json"), (what, r.headers)
        body = r.json()
        assert set(body) == {"error"} and {"code", "message"} <= set(body["error"]), body
