"""Request body limits enforced while the body streams in: its size and the time it takes.

Size (:class:`BodyLimit`):
A declared ``Content-Length`` over the limit is refused at once (413, nothing read). Otherwise
the ASGI ``receive`` channel is wrapped: once more bytes than the limit have arrived it raises
:class:`BodyTooLarge`, which the app answers with 413 (the rest of the upload is never read
into memory). :class:`BodyTooLarge` is an ``HTTPException`` so that FastAPI's form parsing
passes it on unchanged instead of answering "error parsing the body" (400).

Time (:class:`BodyDeadline`): the whole body must arrive within a deadline counted from its
headers; a ``receive`` still waiting then raises :class:`BodyTimeout` (answered 408, the
connection closed). A client that trickles its upload cannot hold a connection (and the
request's memory) for longer.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import error_body

__all__ = ["BodyDeadline", "BodyLimit", "BodyTimeout", "BodyTooLarge"]


class BodyTooLarge(HTTPException):
    """Raised by the wrapped ``receive`` once a body crosses its limit (answered 413)."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, _message(limit))
        self.limit = limit


def _message(limit: int) -> str:
    return f"request body exceeds {limit} bytes"


class BodyLimit:
    """ASGI middleware: ``limit_for(path)`` bytes at most per request body."""

    def __init__(self, app: ASGIApp, limit_for: Callable[[str], int]) -> None:
        self.app = app
        self.limit_for = limit_for

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope.get("path", ""))
        declared = _content_length(scope)
        if declared is not None and declared > limit:
            await _reject(send, limit)
            return
        seen = 0

        async def limited() -> Message:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge(limit)
            return message

        await self.app(scope, limited, send)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", []):
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


async def _reject(send: Send, limit: int) -> None:
    data = json.dumps(error_body("payload_too_large", _message(limit))).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 413,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(data)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": data})


class BodyTimeout(HTTPException):
    """Raised by the timed ``receive`` once a body is late (answered 408, connection closed)."""

    def __init__(self, timeout_s: float) -> None:
        super().__init__(
            408,
            f"the request body did not arrive within {timeout_s:g} s",
            headers={"Connection": "close"},
        )


class BodyDeadline:
    """ASGI middleware: a request's body must be in ``timeout_s`` seconds after its headers."""

    def __init__(self, app: ASGIApp, timeout_s: float) -> None:
        self.app = app
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout_s
        complete = False

        async def timed() -> Message:
            nonlocal complete
            if complete:  # the body is in: waiting for a disconnect is not timed
                return await receive()
            try:
                async with asyncio.timeout_at(deadline):
                    message = await receive()
            except TimeoutError:
                raise BodyTimeout(self.timeout_s) from None
            if message["type"] != "http.request" or not message.get("more_body", False):
                complete = True
            return message

        await self.app(scope, timed, send)
