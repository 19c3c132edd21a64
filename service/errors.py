"""Every error the API answers is JSON ``{"error": {"code": ..., "message": ...}}``.

This module is the one place that builds that body (:func:`error_body`) and maps errors to
HTTP: our own :class:`ApiError`, FastAPI's validation errors (422), a body over the limit
(413, :class:`~service.limits.BodyTooLarge`), a loaded index version found corrupt (503
``index_corrupt``, :class:`~service.engine.IndexVersionCorrupt`), Starlette's HTTP errors
(404, 405, ...), a client that hung up before its request was read (:data:`CLIENT_CLOSED`:
one log line, no answer can reach it) and, as a last resort, any other exception (500 with a
generic message; the traceback goes to the log, never to the client). The constructors below
name the errors several routes raise.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.responses import Response

from service.engine import IndexVersionCorrupt
from service.schemas import ErrorBody

__all__ = [
    "CLIENT_CLOSED",
    "ERROR_RESPONSES",
    "ApiError",
    "error_body",
    "index_corrupt",
    "install_handlers",
    "invalid_request",
    "malformed_body",
    "overloaded",
    "upload_too_large",
]

log = logging.getLogger("hmpf.service")

#: The status recorded (metrics, access log) for a request whose client hung up before it was
#: read: nginx's 499 "client closed request". Never sent: nobody is there to read it.
CLIENT_CLOSED = 499

#: The error answers the API's routes document (``responses=`` of a route or router).
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody} for code in (401, 403, 413, 415, 422, 503)
}


class ApiError(Exception):
    """An error answered with ``status`` and a stable machine-readable ``code``."""

    def __init__(
        self, status: int, code: str, message: str, headers: dict[str, str] | None = None
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.headers = headers

    def response(self) -> JSONResponse:
        return JSONResponse(
            error_body(self.code, self.message), status_code=self.status, headers=self.headers
        )


def error_body(code: str, message: str) -> dict[str, Any]:
    """The JSON body of every error answer."""
    return {"error": {"code": code, "message": message}}


def invalid_request(message: str) -> ApiError:
    return ApiError(422, "invalid_request", message)


def malformed_body(detail: str) -> ApiError:
    """A multipart body the form parser could not read (FastAPI reports it as a 400)."""
    return invalid_request(f"malformed multipart body: {detail}")


def upload_too_large(limit: int, what: str = "image") -> ApiError:
    return ApiError(413, "payload_too_large", f"{what} exceeds the upload limit of {limit} bytes")


def overloaded(retry_after_s: int) -> ApiError:
    return ApiError(
        503,
        "overloaded",
        "all workers are busy and the queue is full; retry later",
        {"Retry-After": str(retry_after_s)},
    )


def index_corrupt(version: str) -> ApiError:
    """The loaded version failed its background check (:class:`IndexVersionCorrupt`)."""
    return ApiError(
        503,
        "index_corrupt",
        f"index version {version} is corrupt (a file differs from the sha256 its manifest "
        "lists) and this server answers nothing from it; operators: run `hmpf-index verify` "
        "on the index, switch to a sound version with `hmpf-index use VERSION` (or rebuild), "
        "then reload (POST /v1/index/reload, or wait for the watch on CURRENT)",
    )


_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    408: "request_timeout",
    413: "payload_too_large",
    415: "unsupported_media_type",
}


def validation_message(errors: Sequence[Any]) -> str:
    """``field: problem; ...`` for the first five of pydantic's / FastAPI's error dicts."""
    parts = []
    for err in list(errors)[:5]:
        loc = ".".join(str(x) for x in err.get("loc", ()) if x not in ("body", "query"))
        parts.append(f"{loc or 'request'}: {err.get('msg', 'invalid')}")
    return "; ".join(parts) or "invalid request"


def install_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return exc.response()

    @app.exception_handler(IndexVersionCorrupt)
    async def _corrupt(request: Request, exc: IndexVersionCorrupt) -> JSONResponse:
        return index_corrupt(exc.version).response()

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        return invalid_request(validation_message(exc.errors())).response()

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # Also answers BodyTooLarge (an HTTPException with status 413).
        code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
        return JSONResponse(error_body(code, str(exc.detail)), exc.status_code, headers=exc.headers)

    @app.exception_handler(ClientDisconnect)
    async def _client_closed(request: Request, exc: ClientDisconnect) -> Response:
        log.info(
            "client disconnected before its request was read: %s %s",
            request.method,
            request.url.path,
        )
        return Response(status_code=CLIENT_CLOSED)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal", "internal error; see the service log"), 500)
