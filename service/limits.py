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

Two limits on the request as a whole are checked before anything else reads it:

* its request line and headers (:class:`HeadLimit`): over ``max_header_bytes`` is a 431, the
  connection closed. h11 only bounds headers that arrive in pieces; ones that come in one
  read (up to the socket's read size, 64 KiB or more) reach the app whole, so they are
  measured here;
* requests in progress at once (:class:`ActiveLimit`): one more than ``max_connections`` is a
  503 with ``Retry-After``, except the probes (``/healthz``, ``/readyz``, ``/metrics``), which
  are always answered: a load balancer must not take a busy replica for a dead one.

Every refusal here is the API's JSON error (:func:`answer_error`).
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import error_body

__all__ = [
    "PROBES",
    "ActiveLimit",
    "BodyDeadline",
    "BodyLimit",
    "BodyTimeout",
    "BodyTooLarge",
    "HeadLimit",
    "answer_error",
    "head_bytes",
]

#: Paths answered whatever the load (cheap, and what load balancers and monitoring poll).
PROBES = frozenset({"/healthz", "/readyz", "/metrics"})


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
    await answer_error(send, 413, "payload_too_large", _message(limit), close=True)


async def answer_error(
    send: Send,
    status: int,
    code: str,
    message: str,
    headers: dict[str, str] | None = None,
    close: bool = False,
) -> None:
    """Send the API's JSON error from an ASGI middleware (before the app has the request);
    ``close``: the connection is closed after it (its body, if any, is not read)."""
    data = json.dumps(error_body(code, message)).encode()
    head = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(data)).encode()),
    ]
    head += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    if close:
        head.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": data})


def head_bytes(scope: Scope) -> int:
    """Bytes of the request line and headers as the client sent them (less any optional
    whitespace): ``METHOD target HTTP/x.y CRLF`` + ``name: value CRLF`` each + ``CRLF``."""
    target = len(scope.get("raw_path") or scope["path"].encode())
    if scope.get("query_string"):
        target += 1 + len(scope["query_string"])
    line = len(scope["method"]) + 1 + target + len(" HTTP/1.1\r\n")
    return line + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ())) + 2


class HeadLimit:
    """ASGI middleware: a request whose line and headers exceed ``limit`` bytes is a 431."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and head_bytes(scope) > self.limit:
            await answer_error(
                send,
                431,
                "request_header_too_large",
                f"the request line and headers exceed {self.limit} bytes",
                close=True,
            )
            return
        await self.app(scope, receive, send)


class ActiveLimit:
    """ASGI middleware: at most ``limit`` requests in progress (headers in, answer not yet
    sent); one more is a 503 with ``Retry-After``. :data:`PROBES` are not counted nor refused.

    Connections that carry no request (idle ones) are bounded apart, by the connection
    protocol (:class:`service.server.GuardedH11`), so they cannot take these places.
    """

    def __init__(self, app: ASGIApp, limit: int, retry_after_s: int) -> None:
        self.app = app
        self.limit = limit
        self.retry_after_s = retry_after_s
        self.active = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in PROBES:
            await self.app(scope, receive, send)
            return
        if self.active >= self.limit:
            await answer_error(
                send,
                503,
                "overloaded",
                f"{self.limit} requests are in progress; retry shortly",
                {"Retry-After": str(self.retry_after_s)},
                close=True,
            )
            return
        self.active += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.active -= 1


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
