"""A Python client of ``hmpf-serve`` for the vehicle side: :class:`Client` and
:class:`AsyncClient` (httpx).

    from hmpf.client import Client

    with Client("http://127.0.0.1:8000", api_key) as service:
        answer = service.localize("frame.jpg", vehicle_id="car-17", timestamp=12.5)
        if answer.match is not None and answer.match.accepted:
            print(answer.match.name, answer.match.lat, answer.match.lon)

* Answers are the pydantic wire models the service answers with (:mod:`hmpf.api`):
  :class:`~hmpf.api.LocalizeResponse`, :class:`~hmpf.api.BatchResponse`,
  :class:`~hmpf.api.IndexInfo`, parsed from the JSON the service sent.
* An image is a path, the bytes of a JPEG, PNG or WebP file, or an RGB (or grey) ``uint8``
  array, encoded here (JPEG by default, ``array_format="png"`` for lossless).
* Sequence mode: the client keeps each vehicle's ``track`` token (``sequence.track`` of its
  last answer, or a batch's ``track``) in :attr:`Client.tracks` and sends it with that
  vehicle's next frame; a token the service refuses (422 ``invalid_track``) is dropped, so
  the vehicle's next frame starts a new track. Send one vehicle's frames one after the other
  (the service keeps no state: the token is the whole track). ``tracks`` is a plain dict, to
  be saved and restored across restarts of the vehicle's program if wanted.
* Retries: a connection error, a timeout or a 503 is tried again, up to ``retries`` more
  times, after ``backoff * 2**n`` seconds (at most ``max_backoff``, times a random factor in
  [0.5, 1] with ``jitter``); a 503's ``Retry-After`` (seconds or an HTTP date) replaces that
  wait (also at most ``max_backoff``). The service keeps no state between requests, so a
  frame sent twice (its answer lost to a timeout) is answered twice, the same way. Any other
  error answer (4xx, 500) is never retried.
* Errors: :class:`ServiceError` (the service answered an error: ``status``, ``code``,
  ``message`` and the JSON ``body``), :class:`ServiceUnreachable` (no answer after every
  try), :class:`UnexpectedAnswer` (a 2xx body that is not the documented model); all are
  :class:`ClientError`, a :class:`~hmpf.errors.HmpfError`. Bad arguments (an array that is
  not an image, no images) raise ``TypeError`` / ``ValueError`` before anything is sent.

OpenCV is imported only to encode an array; torch never.
"""

from __future__ import annotations

import asyncio
import email.utils
import itertools
import math
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Generic, Literal, Self, TypedDict, TypeVar, Unpack

import httpx
import numpy as np
from pydantic import BaseModel, ValidationError

from hmpf.api import (
    TRACK_HEADER,
    VEHICLE_ID_HEADER,
    BatchResponse,
    IndexInfo,
    LocalizeResponse,
)
from hmpf.errors import HmpfError

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

__all__ = [
    "API_KEY_HEADER",
    "TRACK_HEADER",
    "VEHICLE_ID_HEADER",
    "AsyncClient",
    "BatchOptions",
    "Client",
    "ClientError",
    "ImageInput",
    "LocalizeOptions",
    "ServiceError",
    "ServiceUnreachable",
    "UnexpectedAnswer",
    "encode_image",
]

#: The header that carries the API key.
API_KEY_HEADER = "X-API-Key"
#: An image as the client takes it: a file path, encoded bytes, or an RGB / grey uint8 array.
ImageInput = str | os.PathLike[str] | bytes | bytearray | memoryview | np.ndarray
#: Transport errors worth another try: timeouts, refused / reset connections, a connection
#: closed without an answer (not, e.g., an unsupported URL scheme).
_TRANSIENT = (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)
_Http = TypeVar("_Http", httpx.Client, httpx.AsyncClient)
_MAGIC = (
    (b"\xff\xd8\xff", "image/jpeg"),
    (b"\x89PNG\r\n\x1a\n", "image/png"),
)


class BatchOptions(TypedDict, total=False):
    """Optional fields of a request (see ``/docs`` of the service); None means not given.

    ``lat``, ``lon`` and ``radius_m`` (a GPS prior) go together; ``vehicle_id`` turns on
    sequence mode; ``track`` overrides the token the client keeps for that vehicle."""

    lat: float | None
    lon: float | None
    radius_m: float | None
    top_k: int | None
    vehicle_id: str | None
    track: str | None


class LocalizeOptions(BatchOptions, total=False):
    """:class:`BatchOptions` and, for one frame in sequence mode, its capture ``timestamp``
    (seconds, any epoch, the same for all of the vehicle's frames)."""

    timestamp: float | None


class ClientError(HmpfError):
    """Base class of the errors :class:`Client` raises about a request."""


class ServiceError(ClientError):
    """The service answered with an error status.

    Attributes:
        status: the HTTP status (401, 403, 413, 415, 422, 503, ...).
        code: the error's machine-readable code (``unauthorized``, ``invalid_track``, ...),
            ``http_<status>`` when the body is not the service's error JSON.
        message: the service's message.
        body: the JSON body as sent (``{"error": {"code", "message"}}``), or None.
        retry_after: a 503's ``Retry-After`` in seconds, else None.
    """

    def __init__(
        self, status: int, code: str, message: str, body: Any, retry_after: float | None = None
    ) -> None:
        super().__init__(f"{status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message
        self.body = body
        self.retry_after = retry_after

    def __reduce__(self) -> tuple[type, tuple[int, str, str, Any, float | None]]:  # picklable
        return (type(self), (self.status, self.code, self.message, self.body, self.retry_after))


class ServiceUnreachable(ClientError):
    """No answer after every try (connection refused, timeouts, broken connections); the
    last transport error is the ``__cause__``."""


class UnexpectedAnswer(ClientError):
    """A success answer whose body is not the documented model (another service behind the
    URL, or a version this client does not know)."""


def encode_image(
    image: ImageInput, array_format: Literal["jpeg", "png"] = "jpeg"
) -> tuple[bytes, str]:
    """The bytes to upload for ``image`` and their content type.

    A path is read as it is; bytes are sent as they are (JPEG and PNG are labelled by their
    magic numbers, anything else ``application/octet-stream``: the service sniffs the format
    itself and answers 415 / 422 for what it does not accept); an array (``uint8``, H x W RGB,
    H x W x 1 or H x W grey) is encoded as ``array_format`` (JPEG quality 95, or PNG).

    Raises:
        TypeError: not one of those types, or an array that is not ``uint8``.
        ValueError: empty data, or an array of another shape.
        OSError: the file cannot be read.
    """
    if isinstance(image, np.ndarray):
        return _encode_array(image, array_format)
    if isinstance(image, str | os.PathLike):
        data = Path(image).read_bytes()
        what = f"image file {os.fspath(image)!r}"
    elif isinstance(image, bytes | bytearray | memoryview):
        data = bytes(image)
        what = "image bytes"
    else:
        raise TypeError(
            f"image: a path, bytes or a numpy array expected, got {type(image).__name__}"
        )
    if not data:
        raise ValueError(f"{what}: empty")
    for magic, content_type in _MAGIC:
        if data.startswith(magic):
            return data, content_type
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return data, "image/webp"
    return data, "application/octet-stream"


def _encode_array(array: np.ndarray, array_format: str) -> tuple[bytes, str]:
    if array.dtype != np.uint8:
        raise TypeError(f"image array: dtype uint8 expected, got {array.dtype}")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[:, :, 0]
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)) or array.size == 0:
        raise ValueError(
            f"image array: H x W (grey) or H x W x 3 (RGB) expected, got {array.shape}"
        )
    if array_format not in ("jpeg", "png"):
        raise ValueError(f"array_format: 'jpeg' or 'png', got {array_format!r}")
    import cv2  # OpenCV takes ~0.3 s to import: loaded on first use

    bgr = array if array.ndim == 2 else cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if array_format == "jpeg" else []
    ok, buf = cv2.imencode(f".{'jpg' if array_format == 'jpeg' else 'png'}", bgr, params)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image of these shapes
        raise ValueError(f"image array: OpenCV could not encode it as {array_format}")
    return buf.tobytes(), f"image/{array_format}"


@dataclass
class _Call:
    """One API call: the request to send, the model of its answer, the vehicle it is for."""

    request: httpx.Request
    model: type[BaseModel]
    vehicle_id: str | None = None


class _Core:
    """What :class:`Client` and :class:`AsyncClient` share: requests built, waits between
    tries decided, answers parsed and the vehicles' tracks kept. No I/O here."""

    def __init__(
        self,
        url: str,
        api_key: str | None,
        retries: int,
        backoff: float,
        max_backoff: float,
        jitter: bool,
        array_format: Literal["jpeg", "png"],
        timeout: float,
    ) -> None:
        if not url.startswith(("http://", "https://")):
            raise ValueError(f"url: http:// or https:// expected, got {url!r}")
        if retries < 0 or backoff < 0 or max_backoff < 0:
            raise ValueError("retries, backoff and max_backoff must not be negative")
        self.url = url.rstrip("/")
        self.headers = {API_KEY_HEADER: api_key} if api_key else {}
        self.retries = retries
        self.backoff = backoff
        self.max_backoff = max_backoff
        self.jitter = jitter
        self.array_format = array_format
        # on each request: httpx applies a client's timeout only to requests it built
        self.extensions = {"timeout": httpx.Timeout(timeout).as_dict()}
        self.tracks: dict[str, str] = {}

    # -- requests -------------------------------------------------------------------------
    def _request(
        self, method: str, path: str, options: Mapping[str, Any], **kw: Any
    ) -> httpx.Request:
        params: dict[str, Any] = {k: v for k, v in options.items() if v is not None}
        # the vehicle's id and track token travel in headers: URLs end up in logs
        vehicle = params.pop("vehicle_id", None)
        track = params.pop("track", None)
        if vehicle is not None and track is None:
            track = self.tracks.get(vehicle)
        headers = {**self.headers, **kw.pop("headers", {})}
        if vehicle is not None:
            headers[VEHICLE_ID_HEADER] = vehicle
        if track is not None:
            headers[TRACK_HEADER] = track
        return httpx.Request(
            method,
            self.url + path,
            params=params,
            headers=headers,
            extensions=self.extensions,
            **kw,
        )

    def localize(self, image: ImageInput, options: LocalizeOptions) -> _Call:
        """``POST /v1/localize``: the image as the raw body, the fields in the query string (the
        vehicle's id and track in headers)."""
        _check_options("localize", options, LocalizeOptions.__optional_keys__)
        data, content_type = encode_image(image, self.array_format)
        request = self._request(
            "POST", "/v1/localize", options, content=data, headers={"Content-Type": content_type}
        )
        return _Call(request, LocalizeResponse, options.get("vehicle_id"))

    def batch(self, images: Iterable[ImageInput], options: BatchOptions) -> _Call:
        """``POST /v1/localize/batch``: multipart ``images`` fields, the fields in the query
        (the vehicle's id and track in headers)."""
        _check_options("localize_batch", options, BatchOptions.__optional_keys__)
        files = []
        for i, image in enumerate(images):
            data, content_type = encode_image(image, self.array_format)
            files.append(("images", (f"image{i}", data, content_type)))
        if not files:
            raise ValueError("images: at least one image expected")
        request = self._request("POST", "/v1/localize/batch", options, files=files)
        return _Call(request, BatchResponse, options.get("vehicle_id"))

    def index(self) -> _Call:
        """``GET /v1/index``."""
        return _Call(self._request("GET", "/v1/index", {}), IndexInfo)

    # -- tries ----------------------------------------------------------------------------
    def wait(self, attempt: int, outcome: httpx.Response | httpx.TransportError) -> float | None:
        """Seconds to wait before trying again after try ``attempt`` (0: the first) ended in
        ``outcome``; None: no more tries (an answer to return or raise, or tries used up)."""
        if isinstance(outcome, httpx.Response):
            retryable = outcome.status_code == 503
        else:
            retryable = isinstance(outcome, _TRANSIENT)
        if not retryable or attempt >= self.retries:
            return None
        delay = min(self.max_backoff, self.backoff * 2.0**attempt)
        if self.jitter:
            delay *= random.uniform(0.5, 1.0)
        if isinstance(outcome, httpx.Response):
            after = _retry_after(outcome)
            if after is not None:
                delay = min(self.max_backoff, after)
        return delay

    def finish(
        self, call: _Call, outcome: httpx.Response | httpx.TransportError, tries: int
    ) -> Any:
        """The call's answer as its model, its track kept; or the error it ended in after
        ``tries`` tries."""
        if isinstance(outcome, httpx.TransportError):
            raise ServiceUnreachable(
                f"no answer from {self.url} after {tries} tr{'y' if tries == 1 else 'ies'}: "
                f"{type(outcome).__name__}: {outcome}"
            ) from outcome
        if not outcome.is_success:
            error = _service_error(outcome)
            if error.code == "invalid_track" and call.vehicle_id is not None:
                self.tracks.pop(call.vehicle_id, None)  # the service says: start again
            raise error
        try:
            answer = call.model.model_validate_json(outcome.content)
        except ValidationError as exc:
            raise UnexpectedAnswer(
                f"{outcome.request.method} {outcome.request.url.path}: the answer is not a "
                f"{call.model.__name__}: {exc.error_count()} errors, first: "
                f"{exc.errors()[0]['msg']} at {exc.errors()[0]['loc']}"
            ) from None
        track = _track_of(answer)
        if call.vehicle_id is not None and track is not None:
            self.tracks[call.vehicle_id] = track
        return answer


def _check_options(call: str, options: Mapping[str, Any], known: frozenset[str]) -> None:
    unknown = sorted(set(options) - known)
    if unknown:
        raise TypeError(
            f"{call}() got an unexpected keyword argument {unknown[0]!r} (it takes "
            f"{', '.join(sorted(known))})"
        )


def _track_of(answer: BaseModel) -> str | None:
    if isinstance(answer, LocalizeResponse):
        return answer.sequence.track if answer.sequence is not None else None
    if isinstance(answer, BatchResponse):
        return answer.track
    return None


def _retry_after(response: httpx.Response) -> float | None:
    """A response's ``Retry-After`` in seconds (a number or an HTTP date), or None."""
    value = response.headers.get("Retry-After")
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = email.utils.parsedate_to_datetime(value)
        except (TypeError, ValueError):
            return None
        seconds = when.timestamp() - time.time()
    return max(0.0, seconds) if math.isfinite(seconds) else None


def _service_error(response: httpx.Response) -> ServiceError:
    try:
        body = response.json()
    except ValueError:
        body = None
    error = body.get("error") if isinstance(body, dict) else None
    if isinstance(error, dict) and "code" in error:
        code, message = str(error["code"]), str(error.get("message", ""))
    else:
        code = f"http_{response.status_code}"
        message = response.text[:200] or response.reason_phrase
    after = _retry_after(response) if response.status_code == 503 else None
    return ServiceError(response.status_code, code, message, body, after)


class _Base(Generic[_Http]):
    """What both clients have besides their I/O: the arguments, a :class:`_Core`, the
    tracks."""

    def __init__(
        self,
        url: str,
        api_key: str | None = None,
        *,
        timeout: float = 30.0,
        retries: int = 3,
        backoff: float = 0.25,
        max_backoff: float = 10.0,
        jitter: bool = True,
        array_format: Literal["jpeg", "png"] = "jpeg",
    ) -> None:
        core = _Core(url, api_key, retries, backoff, max_backoff, jitter, array_format, timeout)
        self._core = core
        self._http: _Http = self._connect()

    def _connect(self) -> _Http:
        raise NotImplementedError

    @property
    def url(self) -> str:
        """The service's base URL."""
        return self._core.url

    @property
    def tracks(self) -> dict[str, str]:
        """``vehicle_id`` -> the track token its next frame will carry (a live dict: remove a
        vehicle to start its track afresh, set one to resume a saved track)."""
        return self._core.tracks


class Client(_Base[httpx.Client]):
    """A synchronous client of ``hmpf-serve``; one per process is enough (thread-safe, pooled
    connections), closed by :meth:`close` or a ``with`` block.

    Args:
        url: the service's base URL, e.g. ``http://127.0.0.1:8000``.
        api_key: a vehicle (or admin) key, sent as ``X-API-Key``; None where auth is off.
        timeout: seconds for each of connect, write, read and pool wait, per try.
        retries: tries after the first on a connection error, a timeout or a 503.
        backoff: the wait before the first retry (doubled for each further one).
        max_backoff: the longest wait between two tries (Retry-After included).
        jitter: multiply each backoff wait by a random factor in [0.5, 1].
        array_format: how an array image is encoded for upload.
    """

    def _connect(self) -> httpx.Client:
        return httpx.Client()

    def localize(self, image: ImageInput, **options: Unpack[LocalizeOptions]) -> LocalizeResponse:
        """Localise one frame (``POST /v1/localize``).

        With ``vehicle_id`` the request is in sequence mode and carries that vehicle's track;
        the answer's ``match`` is then the sequence estimate (see ``match_source``).

        Raises:
            ServiceError: the service refused the request (never retried unless a 503).
            ServiceUnreachable: no answer after every try.
        """
        answer: LocalizeResponse = self._call(self._core.localize(image, options))
        return answer

    def localize_batch(
        self, images: Iterable[ImageInput], **options: Unpack[BatchOptions]
    ) -> BatchResponse:
        """Localise several frames in one request (``POST /v1/localize/batch``), answered in
        order; one set of fields for all. A bad image gets its own error entry
        (``results[i].error``), not an exception. In sequence mode the frames are one
        vehicle's, consecutive (no timestamps), and the batch's ``track`` is kept."""
        answer: BatchResponse = self._call(self._core.batch(images, options))
        return answer

    def index(self) -> IndexInfo:
        """The loaded index version (``GET /v1/index``)."""
        answer: IndexInfo = self._call(self._core.index())
        return answer

    def _call(self, call: _Call) -> Any:
        for attempt in itertools.count():
            outcome: httpx.Response | httpx.TransportError
            try:
                outcome = self._http.send(call.request)
            except httpx.TransportError as exc:
                outcome = exc
            delay = self._core.wait(attempt, outcome)
            if delay is None:
                return self._core.finish(call, outcome, attempt + 1)
            time.sleep(delay)

    def close(self) -> None:
        """Close the pooled connections."""
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class AsyncClient(_Base[httpx.AsyncClient]):
    """:class:`Client` for asyncio: the same arguments, behaviour and errors; its methods are
    coroutines, ``async with`` / :meth:`aclose` close it."""

    def _connect(self) -> httpx.AsyncClient:
        return httpx.AsyncClient()

    async def localize(
        self, image: ImageInput, **options: Unpack[LocalizeOptions]
    ) -> LocalizeResponse:
        """As :meth:`Client.localize`."""
        answer: LocalizeResponse = await self._call(self._core.localize(image, options))
        return answer

    async def localize_batch(
        self, images: Iterable[ImageInput], **options: Unpack[BatchOptions]
    ) -> BatchResponse:
        """As :meth:`Client.localize_batch`."""
        answer: BatchResponse = await self._call(self._core.batch(images, options))
        return answer

    async def index(self) -> IndexInfo:
        """As :meth:`Client.index`."""
        answer: IndexInfo = await self._call(self._core.index())
        return answer

    async def _call(self, call: _Call) -> Any:
        for attempt in itertools.count():
            outcome: httpx.Response | httpx.TransportError
            try:
                outcome = await self._http.send(call.request)
            except httpx.TransportError as exc:
                outcome = exc
            delay = self._core.wait(attempt, outcome)
            if delay is None:
                return self._core.finish(call, outcome, attempt + 1)
            await asyncio.sleep(delay)

    async def aclose(self) -> None:
        """Close the pooled connections."""
        await self._http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()
