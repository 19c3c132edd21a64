"""The limits of one service in its OpenAPI document.

Some limits the routes enforce are settings (``max_top_k``, ``max_batch``, ``max_pixels``,
``max_upload_bytes``), so FastAPI's document, generated from the request models, cannot hold
them. :func:`document_limits` has the app's ``/openapi.json`` say them: the maximum of
``top_k`` (query parameter and form field), the number of images of a batch and the image
size limits (in the descriptions of the uploads: a binary body has no JSON Schema keyword
for pixels or bytes). It also drops the ``null`` that pydantic offers for an optional field:
a query parameter or form field cannot be null, it is left out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from service.settings import Settings

__all__ = ["MIN_IMAGE_SIDE", "document_limits", "image_limits"]

#: Narrower images are refused (422 ``invalid_image``; :func:`service.images.decode_upload`).
MIN_IMAGE_SIDE = 2
_ROUTES = ("/v1/localize", "/v1/localize/batch", "/v1/evidence")
_MULTIPART = "multipart/form-data"


def image_limits(settings: Settings) -> str:
    """What an uploaded image must be, in words."""
    side = MIN_IMAGE_SIDE
    return (
        f"JPEG, PNG or WebP, at least {side} x {side} and at most {settings.max_pixels} pixels "
        f"(width x height, read from the header), at most {settings.max_upload_bytes} bytes"
    )


def document_limits(app: FastAPI, settings: Settings) -> None:
    """Make ``app.openapi()`` (``/openapi.json``, ``/docs``) state ``settings``' limits."""
    generate: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            _apply(generate(), settings)
        return app.openapi_schema or {}

    app.openapi = openapi  # type: ignore[method-assign]


def _apply(doc: dict[str, Any], settings: Settings) -> None:
    images = image_limits(settings)
    for path in _ROUTES:
        op = doc.get("paths", {}).get(path, {}).get("post")
        if op is None:
            continue
        for param in op.get("parameters", []):
            param["schema"] = _without_null(param["schema"])
            if param["name"] == "top_k":
                param["schema"]["maximum"] = settings.max_top_k
        body = op.get("requestBody", {})
        if set(body.get("content", {})) - {_MULTIPART}:
            body["description"] = (
                f"multipart form, or the camera frame as the body (image content types): {images}"
            )
        if _MULTIPART in body.get("content", {}):
            form = _deref(doc, body["content"][_MULTIPART]["schema"])["properties"]
            for name, schema in form.items():
                form[name] = _without_null(schema)
            if "top_k" in form:
                form["top_k"]["maximum"] = settings.max_top_k
            if "image" in form:
                form["image"]["description"] = f"the camera frame: {images}"
            if "images" in form:
                form["images"]["maxItems"] = settings.max_batch
                form["images"]["description"] = (
                    f"1 to {settings.max_batch} frames, answered in order; each: {images}"
                )


def _without_null(schema: dict[str, Any]) -> dict[str, Any]:
    """``anyOf: [X, null]`` (pydantic's ``X | None``) as X, keeping the title and description."""
    branches = schema.get("anyOf")
    if not branches:
        return schema
    kept = [b for b in branches if b.get("type") != "null"]
    if len(kept) != 1 or len(kept) == len(branches):
        return schema
    outer = {k: v for k, v in schema.items() if k not in ("anyOf", "default")}
    return {**kept[0], **outer}


def _deref(doc: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    ref = schema.get("$ref")
    if ref is None:
        return schema
    found: dict[str, Any] = doc["components"]["schemas"][ref.rsplit("/", 1)[-1]]
    return found
