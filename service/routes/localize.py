"""``POST /v1/localize`` (one image) and ``POST /v1/localize/batch`` (several, in order).

``/v1/localize`` takes its image in one of two ways, served by two routes on the same path:

* a multipart form, field ``image`` (a :class:`MultipartRoute`, which matches only
  ``multipart/form-data`` requests); its OpenAPI operation lists the raw-body content types
  too (:data:`RAW_BODY_TYPES`), so ``/docs`` describes both ways;
* the raw body with an image content type (the route after it, hidden from the schema).

The optional fields (:class:`~service.schemas.LocalizeFields`) may come as query parameters
or, with multipart, as form fields; a field given twice is refused. A vehicle's id and track
token (:class:`~service.schemas.VehicleFields`) come in the ``X-Vehicle-Id`` and ``X-Track``
headers or as form fields, never in the URL (422): URLs end up in logs. A batch runs its images
in up to ``workers`` lanes, one admission slot each, and answers a bad image with its own
error entry while the others are answered.

With a ``vehicle_id`` a request is in sequence mode (:mod:`service.vehicle`): its ``track``
token is checked before the images run, and the sequence filter runs over the answers, in
order, after them.

With recording on (setting ``experience_log``), each final answer and its uploaded bytes are
then offered to the app's :class:`~service.recording.Recorder`, which keeps the confidently
accepted ones for the map (it never waits or fails the request).
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Coroutine
from typing import Annotated, Any, NamedTuple, NoReturn

from fastapi import APIRouter, Depends, Form, Header, Query, Request, UploadFile
from fastapi.routing import APIRoute
from pydantic import Field, ValidationError
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import Response
from starlette.routing import Match
from starlette.types import Scope

from service.deps import (
    API_KEY_HEADER,
    EngineDep,
    MetricsDep,
    SettingsDep,
    TrackerDep,
    VehicleKey,
    authorize,
)
from service.engine import Engine
from service.errors import (
    ERROR_RESPONSES,
    ApiError,
    invalid_request,
    malformed_body,
    overloaded,
    upload_too_large,
    validation_message,
)
from service.images import ACCEPTED_TYPES, check_content_type, check_decode_budget
from service.metrics import Metrics
from service.query import ImageQuery
from service.recording import Recorder
from service.schemas import (
    TRACK_HEADER,
    VEHICLE_ID_HEADER,
    VEHICLE_ID_PATTERN,
    BatchItem,
    BatchResponse,
    ErrorDetail,
    LocalizeFields,
    LocalizeParams,
    LocalizeResponse,
    VehicleFields,
)
from service.settings import Settings
from service.track import MAX_TOKEN_CHARS
from service.vehicle import Tracker

__all__ = ["RAW_BODY_TYPES", "BatchForm", "FormRoute", "LocalizeForm", "MultipartRoute", "router"]

log = logging.getLogger("hmpf.service")

_MULTIPART = "multipart/form-data"
#: Content types of a raw-body image (the bytes are sniffed; octet-stream is accepted too).
RAW_BODY_TYPES = (*ACCEPTED_TYPES, "application/octet-stream")


class LocalizeForm(LocalizeFields, VehicleFields):
    """The multipart form of ``POST /v1/localize``."""

    image: UploadFile = Field(description="the camera frame: JPEG, PNG or WebP")


class BatchForm(LocalizeFields, VehicleFields):
    """The multipart form of ``POST /v1/localize/batch`` (one set of fields for all images)."""

    images: list[UploadFile] = Field(
        min_length=1, description="one or more frames, answered in order"
    )


class FormRoute(APIRoute):
    """A route with a form body, read (by FastAPI) before the key is checked.

    A body the parser cannot read is a 422 like every invalid request (``invalid_request``)
    rather than FastAPI's 400, but a client that hung up is a disconnect, not a bad body; and,
    as for a body that parses, a caller without a key for :attr:`role` hears 401 / 403
    instead of what is wrong with its body (or its size).
    """

    #: The role the route's key dependency asks for.
    role = "vehicle"

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def key_first_parse_errors_422(request: Request) -> Response:
            try:
                return await handler(request)
            except HTTPException as exc:
                if isinstance(exc.__cause__, ClientDisconnect):  # FastAPI's 400 for it
                    raise exc.__cause__ from None
                if exc.status_code not in (400, 413):
                    raise
                authorize(request, request.headers.get(API_KEY_HEADER), self.role)
                if exc.status_code == 413:
                    raise
                raise malformed_body(str(exc.detail)) from None

        return key_first_parse_errors_422


class MultipartRoute(FormRoute):
    """A :class:`FormRoute` for ``multipart/form-data`` requests only: another request does
    not match it, so the next route on the same path and method takes it."""

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        match, child = super().matches(scope)
        if match is Match.FULL and not _is_multipart(scope):
            return Match.NONE, {}
        return match, child


def _is_multipart(scope: Scope) -> bool:
    for name, value in scope.get("headers", ()):
        if name == b"content-type":
            return value.decode("latin-1").startswith(_MULTIPART)
    return False


async def _raw_content_type(request: Request) -> str:
    """The raw body's declared image type (415 for another type, or none)."""
    declared = request.headers.get("content-type", "")
    check_content_type(declared or None)
    if not declared:
        raise ApiError(
            415,
            "unsupported_media_type",
            "send the image as multipart field 'image' or as the body with "
            "Content-Type image/jpeg, image/png or image/webp",
        )
    return declared


def _binary_bodies() -> dict[str, Any]:
    """The OpenAPI request bodies of a raw-body image, one per accepted content type."""
    return {t: {"schema": {"type": "string", "format": "binary"}} for t in RAW_BODY_TYPES}


QueryFields = Annotated[LocalizeFields, Query()]


async def _vehicle_headers(
    request: Request,
    vehicle_id: Annotated[
        str | None,
        Header(
            alias=VEHICLE_ID_HEADER,
            min_length=1,
            max_length=128,
            pattern=VEHICLE_ID_PATTERN,
            description=VehicleFields.model_fields["vehicle_id"].description,
        ),
    ] = None,
    track: Annotated[
        str | None,
        Header(
            alias=TRACK_HEADER,
            min_length=1,
            max_length=MAX_TOKEN_CHARS,
            description=VehicleFields.model_fields["track"].description,
        ),
    ] = None,
) -> dict[str, str]:
    """The vehicle's id and track from their headers; 422 for either in the query string
    (the access log blanks them there: :class:`service.server.RedactAccessLog`)."""
    for name, header in (("vehicle_id", VEHICLE_ID_HEADER), ("track", TRACK_HEADER)):
        if name in request.query_params:
            raise invalid_request(
                f"{name}: send it in the {header} header (or a multipart form field), "
                "never in the URL"
            )
    given = {"vehicle_id": vehicle_id, "track": track}
    return {k: v for k, v in given.items() if v is not None}


VehicleHeaders = Annotated[dict[str, str], Depends(_vehicle_headers)]


class Upload(NamedTuple):
    """One uploaded image as read from the request."""

    data: bytes
    content_type: str | None
    source: str  # how messages name it: image, images[3]


class Localizer:
    """What the localisation routes use of the app: admit, run and answer images."""

    def __init__(
        self,
        engine: Engine,
        settings: Settings,
        metrics: Metrics,
        tracker: Tracker,
        recorder: Recorder | None = None,
    ) -> None:
        self.engine = engine
        self.settings = settings
        self.metrics = metrics
        self.tracker = tracker
        self.recorder = recorder

    def check(self, params: LocalizeParams) -> None:
        """422 for a ``top_k`` over the service's limit."""
        limit = self.settings.max_top_k
        if params.top_k > limit:
            raise invalid_request(f"top_k: at most {limit} (got {params.top_k})")

    def check_size(self, upload: UploadFile, what: str) -> None:
        """413 for an uploaded file over the limit, from its parsed size, before reading it."""
        if upload.size is not None and upload.size > self.settings.max_upload_bytes:
            raise upload_too_large(self.settings.max_upload_bytes, what)

    def queries(
        self, params: LocalizeParams, uploads: list[Upload], sequence: bool = False
    ) -> list[ImageQuery]:
        """Admitted work for each upload: 413 over the size limit or the decode budget, 503
        when the slots are taken (a batch takes one per lane, at most ``workers``);
        ``sequence``: keep each frame's evidence for the sequence filter."""
        limit = self.settings.max_upload_bytes
        for upload in uploads:
            if len(upload.data) > limit:
                raise upload_too_large(limit, upload.source)
        side = self.settings.decode_side
        budget, pixels = self.settings.max_decode_bytes, self.settings.max_pixels
        check_decode_budget([u.data for u in uploads], budget, side, pixels)
        if not self.engine.admit(self.lanes(len(uploads))):
            raise overloaded(self.settings.retry_after_s)
        compute = self.engine.compute
        # recording on: each image keeps its features for the log (a merge then need not
        # extract them); packed on the recorder's thread, never on the request's path
        keep = self.recorder is not None and self.settings.experience_features
        return [
            ImageQuery(
                u.data,
                u.content_type,
                params,
                u.source,
                pixels,
                compute,
                sequence=sequence,
                decode_side=side,
                keep_features=keep,
            )
            for u in uploads
        ]

    def lanes(self, images: int) -> int:
        # A batch runs its images in up to `workers` lanes, one slot each, so that any batch
        # size fits the admission limit and a batch cannot take the queue's slots.
        return min(images, self.engine.workers)

    async def answer(self, params: LocalizeParams, upload: Upload) -> LocalizeResponse:
        """One image's answer (its error raised as the request's)."""
        received = time.time()
        vehicle = self.tracker.open(params)
        queries = self.queries(params, [upload], vehicle is not None)
        ((ok, value),) = await self.engine.run(queries)
        if not ok:
            raise value
        self.metrics.observe_stages(value.timing_ms)
        if vehicle is not None:
            (value,), _ = self.tracker.follow(vehicle, [value], queries)
        answer: LocalizeResponse = value
        self.record(params, upload, answer, received, queries[0])
        return answer

    def record(
        self,
        params: LocalizeParams,
        upload: Upload,
        answer: LocalizeResponse,
        received: float,
        query: ImageQuery,
    ) -> None:
        """Offer a final answer and its frame (with its features, when the query kept them)
        to the recorder (recording on; never waits)."""
        if self.recorder is not None:
            self.recorder.offer(
                answer,
                upload.data,
                upload.content_type,
                params.vehicle_id,
                params.timestamp,
                received,
                query.features,
                query.methods,
            )

    async def answer_batch(self, params: LocalizeParams, uploads: list[Upload]) -> BatchResponse:
        """Every image's answer or error, in order (in sequence mode the frames of one
        vehicle, consecutive: a failed image counts as a dropped frame)."""
        if params.timestamp is not None:
            raise invalid_request(
                "timestamp: a batch's frames count as consecutive; send timed frames one by one"
            )
        received = time.time()
        vehicle = self.tracker.open(params)
        queries = self.queries(params, uploads, vehicle is not None)
        version = self.engine.current.version
        outcomes = await self.engine.run(queries, self.lanes(len(uploads)))
        for ok, value in outcomes:
            if ok:
                self.metrics.observe_stages(value.timing_ms)
                version = value.index_version
        track = None
        if vehicle is not None:
            answers = [value if ok else None for ok, value in outcomes]
            followed, track = self.tracker.follow(vehicle, answers, queries)
            outcomes = [
                (ok, new if ok else value)
                for (ok, value), new in zip(outcomes, followed, strict=True)
            ]
        for upload, query, (ok, value) in zip(uploads, queries, outcomes, strict=True):
            if ok:
                self.record(params, upload, value, received, query)
        items = [_batch_item(i, ok, value) for i, (ok, value) in enumerate(outcomes)]
        return BatchResponse(results=items, index_version=version, track=track)


async def _localizer(
    request: Request,
    engine: EngineDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    tracker: TrackerDep,
) -> Localizer:
    # The recorder lives on the app from its lifespan's start (None: recording off).
    recorder = getattr(request.app.state, "recorder", None)
    return Localizer(engine, settings, metrics, tracker, recorder)


LocalizerDep = Annotated[Localizer, Depends(_localizer)]


async def localize(
    key: VehicleKey,
    request: Request,
    query: QueryFields,
    headers: VehicleHeaders,
    form: Annotated[LocalizeForm, Form(media_type=_MULTIPART)],
    localizer: LocalizerDep,
) -> LocalizeResponse:
    """Localise one image against the current index version.

    Send it as multipart field ``image`` or as the raw body with an image content type; the
    optional fields as query parameters (either way) or form fields (multipart).
    """
    params = await _params(request, query, headers, form)
    localizer.check_size(form.image, "image")
    data = await form.image.read()
    localizer.check(params)
    answer: LocalizeResponse = await localizer.answer(
        params, Upload(data, form.image.content_type, "image")
    )
    return answer


async def localize_raw_body(
    key: VehicleKey,
    content_type: Annotated[str, Depends(_raw_content_type)],
    request: Request,
    query: QueryFields,
    headers: VehicleHeaders,
    localizer: LocalizerDep,
) -> LocalizeResponse:
    """``/v1/localize`` with the image as the raw body (documented with the multipart route)."""
    params = await _params(request, query, headers, None)
    localizer.check(params)
    data = await request.body()
    answer: LocalizeResponse = await localizer.answer(params, Upload(data, content_type, "image"))
    return answer


async def localize_batch(
    key: VehicleKey,
    request: Request,
    query: QueryFields,
    headers: VehicleHeaders,
    form: Annotated[BatchForm, Form(media_type=_MULTIPART)],
    localizer: LocalizerDep,
) -> BatchResponse:
    """Localise several images (multipart, ``images`` fields); answers in order."""
    params = await _params(request, query, headers, form, repeatable="images")
    for i, upload in enumerate(form.images):
        localizer.check_size(upload, f"images[{i}]")
    uploads = [
        Upload(await f.read(), f.content_type, f"images[{i}]") for i, f in enumerate(form.images)
    ]
    localizer.check(params)
    return await localizer.answer_batch(params, uploads)


def batch_not_multipart(key: VehicleKey) -> NoReturn:
    """``/v1/localize/batch`` with a body that is not multipart: 415 (the body is not read)."""
    raise ApiError(415, "unsupported_media_type", "send the images as multipart fields 'images'")


router = APIRouter(tags=["localize"], responses=ERROR_RESPONSES)
# The multipart route first: it matches only multipart requests, the raw-body route the rest.
router.add_api_route(
    "/v1/localize",
    localize,
    methods=["POST"],
    response_model=LocalizeResponse,
    openapi_extra={"requestBody": {"content": _binary_bodies()}},
    route_class_override=MultipartRoute,
)
router.add_api_route(
    "/v1/localize",
    localize_raw_body,
    methods=["POST"],
    response_model=LocalizeResponse,
    include_in_schema=False,
)
router.add_api_route(
    "/v1/localize/batch",
    localize_batch,
    methods=["POST"],
    response_model=BatchResponse,
    route_class_override=MultipartRoute,
)
router.add_api_route(
    "/v1/localize/batch",
    batch_not_multipart,
    methods=["POST"],
    response_model=None,
    include_in_schema=False,
)


# -- the steps the routes share -------------------------------------------------------------
async def _params(
    request: Request,
    query: LocalizeFields,
    headers: dict[str, str],
    form: LocalizeForm | BatchForm | None,
    repeatable: str = "",
) -> LocalizeParams:
    """The request's fields from the query string, the vehicle headers and the form, checked
    together.

    FastAPI has validated each source on its own (types, ranges, unknown names) but keeps the
    last of repeated values; here a field given more than once (in one source or in two,
    except the ``repeatable`` file field) and a partial GPS prior are refused (422).
    """
    names = [k for k, _ in request.query_params.multi_items()] + list(headers)
    names += [f for h, f in _HEADER_FIELDS.items() if len(request.headers.getlist(h)) > 1]
    if form is not None:
        names += [k for k, _ in (await request.form()).multi_items() if k != repeatable]
    repeated = [name for name, n in Counter(names).items() if n > 1]
    if repeated:
        raise invalid_request(f"{repeated[0]}: given twice")
    fields = set(LocalizeParams.model_fields)
    given = query.model_dump(exclude_unset=True) | headers
    if form is not None:
        given |= form.model_dump(exclude_unset=True, include=fields)
    try:
        return LocalizeParams.model_validate(given)
    except ValidationError as exc:
        raise invalid_request(validation_message(exc.errors())) from None


#: Header -> the field it carries (a header given twice is a field given twice).
_HEADER_FIELDS = {VEHICLE_ID_HEADER: "vehicle_id", TRACK_HEADER: "track"}


def _batch_item(i: int, ok: bool, value: Any) -> BatchItem:
    """Batch entry ``i``: the answer, or the error that one image met (never the batch's)."""
    if ok:
        return BatchItem(index=i, result=value)
    if isinstance(value, ApiError):
        return BatchItem(index=i, error=ErrorDetail(code=value.code, message=value.message))
    log.error("batch item %d failed", i, exc_info=value)
    return BatchItem(index=i, error=ErrorDetail(code="internal", message="internal error"))
