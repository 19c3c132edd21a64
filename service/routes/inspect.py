"""The inspection page and the data it shows besides the answers of ``/v1/localize``.

* ``GET /inspect``: the page (static HTML, CSS and JavaScript from ``service/static``, no
  key needed: it holds no data; every call it makes sends the key the user typed).
* ``GET /v1/references``: every reference's name and position (lat/lon, null without).
* ``GET /v1/references/{reference}/thumbnail``: a reference's thumbnail (JPEG), by name or
  row id; 404 for an unknown reference or one without a thumbnail.
* ``POST /v1/evidence?reference=...``: the local-feature evidence between an uploaded image
  (multipart field ``image``) and a reference, drawn as a PNG (:mod:`service.evidence`).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Form, Query, UploadFile
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response
from pydantic import BaseModel, Field

from hmpf.errors import HmpfError
from service.deps import EngineDep, SettingsDep, VehicleKey
from service.engine import Loaded
from service.errors import ERROR_RESPONSES, ApiError, overloaded, upload_too_large
from service.evidence import evidence_method, render_evidence
from service.images import check_decode_budget, decode_upload
from service.routes.localize import FormRoute
from service.schemas import ErrorBody, ReferenceList
from service.settings import Settings

__all__ = ["MAX_REFERENCE_CHARS", "MAX_ROW_DIGITS", "STATIC", "resolve_reference", "router"]

#: The longest reference (name or row id) a request may give.
MAX_REFERENCE_CHARS = 512
#: The most digits of a row id (an int64's 19 digits; leading zeros beyond are refused).
MAX_ROW_DIGITS = 19
_ROW_ID = re.compile(rf"[0-9]{{1,{MAX_ROW_DIGITS}}}")

#: The page's files (in the wheel: package data of ``service``).
STATIC = Path(__file__).resolve().parent.parent / "static"
_NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "no such reference, or it has no thumbnail"}
}


def _binary(media_type: str, what: str) -> dict[int | str, dict[str, Any]]:
    return {
        200: {
            "description": what,
            "content": {media_type: {"schema": {"type": "string", "format": "binary"}}},
        }
    }


class EvidenceForm(BaseModel):
    """The multipart form of ``POST /v1/evidence``."""

    image: UploadFile = Field(description="the camera frame: JPEG, PNG or WebP")


router = APIRouter(tags=["inspect"], responses=ERROR_RESPONSES)


@router.get("/inspect", include_in_schema=False)
def page() -> FileResponse:
    """The inspection page (no data in it; it asks for a key)."""
    return FileResponse(STATIC / "inspect.html", media_type="text/html")


@router.get("/v1/references", response_model=ReferenceList)
def references(key: VehicleKey, engine: EngineDep) -> ReferenceList:
    """Every place of the loaded version, in place order (its original reference's name and
    position; a fleet experience's image is reached by the row in an answer's
    ``match.experience``)."""
    loaded = engine.lease()
    try:
        reader = loaded.reader
        meta, n = reader.refs.meta, reader.n
        has = loaded.has_positions
        return ReferenceList(
            index_version=loaded.version,
            names=list(reader.place_names),
            lat=[_num(x) for x in meta["lat"][:n]] if has else None,
            lon=[_num(x) for x in meta["lon"][:n]] if has else None,
            thumbnails=loaded.reader.thumbnails is not None,
        )
    finally:
        engine.release(loaded)


def _num(x: float) -> float | None:
    return float(x) if x == x else None  # NaN: no position


@router.get(
    "/v1/references/{reference}/thumbnail",
    response_class=Response,
    responses={**_binary("image/jpeg", "the thumbnail"), **_NOT_FOUND},
)
def thumbnail(
    reference: Annotated[
        str,
        PathParam(
            min_length=1, max_length=MAX_REFERENCE_CHARS, description="reference name or row id"
        ),
    ],
    key: VehicleKey,
    engine: EngineDep,
) -> Response:
    """A reference's thumbnail (JPEG, longest side 160 px), by name or row id."""
    loaded = engine.lease()
    try:
        ref = resolve_reference(loaded, reference)
        data = loaded.reader.thumbnail(ref)
    finally:
        engine.release(loaded)
    if data is None:
        raise ApiError(
            404,
            "no_thumbnail",
            f"reference {reference!r} has no thumbnail (index version {loaded.version} was "
            "built without them; rebuild it to get them)",
        )
    return Response(
        data,
        media_type="image/jpeg",
        headers={"Cache-Control": "private, no-cache", "X-Hmpf-Index-Version": loaded.version},
    )


def resolve_reference(loaded: Loaded, reference: str) -> int:
    """The row of ``reference``: a name of the index, else a row id (404 for neither).

    A row id is ASCII digits only, at most :data:`MAX_ROW_DIGITS` of them: ``str.isdigit``
    also passes ``²`` (which ``int`` refuses) and ``int`` also reads other scripts' digits
    and refuses more than 4,300 digits, so neither decides alone.
    """
    names = loaded.reader.refs.names
    try:
        return names.index(reference)
    except ValueError:
        pass
    if _ROW_ID.fullmatch(reference) and int(reference) < len(names):
        return int(reference)
    raise ApiError(
        404,
        "unknown_reference",
        f"no reference {reference[:80]!r} in index version {loaded.version} (give a name or "
        f"a row id 0..{len(names) - 1})",
    )


async def evidence(
    key: VehicleKey,
    reference: Annotated[
        str,
        Query(min_length=1, max_length=MAX_REFERENCE_CHARS, description="reference name or row id"),
    ],
    form: Annotated[EvidenceForm, Form(media_type="multipart/form-data")],
    engine: EngineDep,
    settings: SettingsDep,
) -> Response:
    """The local-feature evidence between the uploaded image and ``reference``: a PNG with
    the query (left) and the reference's thumbnail (right), matched keypoints (KAZE) or OLO
    regions drawn in pairs. Headers ``X-Hmpf-Evidence-Method`` and ``-Pairs`` say which
    method and how many pairs. 409 when the index has no local method or no thumbnail."""
    limit = settings.max_upload_bytes
    if form.image.size is not None and form.image.size > limit:
        raise upload_too_large(limit, "image")
    data = await form.image.read()
    if len(data) > limit:
        raise upload_too_large(limit, "image")
    check_decode_budget(
        [data], settings.max_decode_bytes, settings.decode_side, settings.max_pixels
    )
    if not engine.admit(1):
        raise overloaded(settings.retry_after_s)
    content_type = form.image.content_type
    ((ok, value),) = await engine.run(
        [lambda loaded: _evidence(loaded, settings, reference, data, content_type)]
    )
    if not ok:
        raise value
    png, method, pairs = value
    return Response(
        png,
        media_type="image/png",
        headers={"X-Hmpf-Evidence-Method": method, "X-Hmpf-Evidence-Pairs": str(pairs)},
    )


def _evidence(
    loaded: Loaded, settings: Settings, reference: str, data: bytes, content_type: str | None
) -> tuple[bytes, str, int]:
    """Render on a query thread (the CNN forward passes run here)."""
    ref = resolve_reference(loaded, reference)
    if evidence_method(loaded.reader) is None:
        raise ApiError(
            409, "no_local_features", "the index has no local method (KAZE or OLO) to draw"
        )
    thumb = loaded.reader.thumbnail(ref)
    if thumb is None:
        raise ApiError(409, "no_thumbnail", f"reference {reference!r} has no thumbnail")
    image = decode_upload(
        data,
        max_pixels=settings.max_pixels,
        content_type=content_type,
        source="image",
        decode_side=settings.decode_side,
    )
    try:
        out = render_evidence(loaded.reader, image, ref, thumb)
    except HmpfError as exc:
        raise ApiError(422, "invalid_image", f"image: {exc}") from None
    return out.png, out.method, out.pairs


router.add_api_route(
    "/v1/evidence",
    evidence,
    methods=["POST"],
    response_class=Response,
    responses={
        **_binary("image/png", "the evidence image"),
        **_NOT_FOUND,
        409: {"model": ErrorBody, "description": "no local method, or no thumbnail"},
    },
    route_class_override=FormRoute,
)
