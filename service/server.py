"""uvicorn as ``hmpf-serve`` runs it: its options from the settings, and a connection protocol
that bounds what a client's connections can hold.

What bounds a client (the settings, :class:`~service.settings.Settings`):

* ``header_timeout_s``: from the connection (or the end of the previous answer on a kept-alive
  connection) to the end of the request's headers; a client that is later gets a 408 and the
  connection is closed (:class:`GuardedH11`; uvicorn has no such timeout: a client that
  opens a connection and sends nothing would keep it for ever). No request reached the app,
  so ``hmpf_requests_total`` does not count it; the log has one line.
* ``body_timeout_s``: the body, once the headers are in (:class:`~service.limits.BodyDeadline`,
  a 408 JSON error).
* ``max_idle_connections``: connections that carry no request (opened and not yet through
  their headers, or kept alive between requests). One more closes the one idle the longest
  (:class:`IdleConnections`): a client holding many idle connections only pushes out its
  own, never the requests in progress nor a new connection that sends its request at once.
  uvicorn's own limit (``limit_concurrency``) counted idle connections with busy ones, so
  200 idle sockets made every other request, health checks included, a 503; it is not used.
* ``max_connections``: requests in progress at once; one more is a 503 JSON error with
  ``Retry-After`` (:class:`~service.limits.ActiveLimit`); the probes (``/healthz``,
  ``/readyz``, ``/metrics``) are always answered. Open connections are at most
  ``max_connections + max_idle_connections`` (plus probes in progress).
* ``keep_alive_s``: an idle kept-alive connection is closed after it (``timeout_keep_alive``).
* ``max_header_bytes``: the request line and headers. Headers that arrive in pieces are cut
  by h11 once over it, headers that arrive in one read are measured whole
  (:class:`~service.limits.HeadLimit`); either way a 431 JSON error, the connection closed.

Every answer of this layer is the API's JSON error: a request h11 cannot parse is a 400
``bad_request`` (uvicorn's own is plain text). The access log never holds a vehicle's track
token or id (:class:`RedactAccessLog`): they travel in headers, and a client that puts them in
the URL anyway is refused (422) with the values blanked in the log line.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import time
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_body

if TYPE_CHECKING:
    from fastapi import FastAPI

    from service.settings import Settings

__all__ = ["GuardedH11", "IdleConnections", "RedactAccessLog", "guarded_protocol", "uvicorn_config"]

log = logging.getLogger("hmpf.service")
#: The graceful shutdown's limit (s): requests in flight get this long to finish.
GRACEFUL_SHUTDOWN_S = 10


def uvicorn_config(app: FastAPI, settings: Settings) -> uvicorn.Config:
    """The uvicorn options of ``hmpf-serve``, from ``settings`` (and the access log's
    redaction, installed on the ``uvicorn.access`` logger once uvicorn has configured it)."""
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        http=guarded_protocol(
            settings.header_timeout_s, settings.max_idle_connections, settings.max_header_bytes
        ),
        ws="none",  # no WebSocket routes: an upgrade request is a plain HTTP request
        # requests in progress are bounded by the app (ActiveLimit), idle connections by the
        # protocol; uvicorn's limit would count both together
        limit_concurrency=None,
        timeout_keep_alive=settings.keep_alive_s,
        h11_max_incomplete_event_size=settings.max_header_bytes,
    )
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactAccessLog) for f in access.filters):
        access.addFilter(RedactAccessLog())
    return config


class RedactAccessLog(logging.Filter):
    """Blanks the values of :data:`SECRET_PARAMS` in the request targets of access-log records
    (uvicorn logs the path with its query string): a track token is a bearer token for a
    vehicle's track and its position belief, a vehicle id names a vehicle."""

    #: Query parameters whose values never reach a log.
    SECRET_PARAMS = ("track", "vehicle_id")
    _pattern = re.compile(r"(?i)([?&;](?:track|vehicle_id)=)[^&;#\s]*")

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(
                self._pattern.sub(r"\1REDACTED", a) if isinstance(a, str) else a
                for a in record.args
            )
        return True


class IdleConnections:
    """A server's connections that carry no request, oldest idle first; past ``limit`` the
    oldest is closed (without an answer: it has no request to answer)."""

    #: Seconds between two log lines about closed idle connections.
    LOG_EVERY_S = 10.0

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._idle: OrderedDict[GuardedH11, None] = OrderedDict()
        self._closed = 0
        self._logged = 0.0

    def __len__(self) -> int:
        return len(self._idle)

    def idle(self, conn: GuardedH11) -> None:
        """``conn`` now carries no request (new, or its answer sent)."""
        self._idle.pop(conn, None)
        self._idle[conn] = None
        while len(self._idle) > self.limit:
            oldest = next(iter(self._idle))
            if oldest is conn:  # pragma: no cover - limit >= 1
                break
            del self._idle[oldest]
            oldest.transport.close()
            self._closed += 1
        self._log()

    def busy(self, conn: GuardedH11) -> None:
        """``conn`` carries a request, or is gone."""
        self._idle.pop(conn, None)

    def _log(self) -> None:
        now = time.monotonic()
        if self._closed and now - self._logged >= self.LOG_EVERY_S:
            log.warning(
                "closed %d idle connections (more than max_idle_connections=%d open)",
                self._closed,
                self.limit,
            )
            self._closed = 0
            self._logged = now


class GuardedH11(H11Protocol):
    """uvicorn's h11 protocol with a deadline for the request headers, a bound on idle
    connections and JSON answers of its own errors.

    The clock starts when the connection opens, and again when an answer has been sent on a
    kept-alive connection; it stops when a request's headers are complete (the app has it,
    and :class:`~service.limits.BodyDeadline` times its body). A client that misses it gets a
    408 and the connection is closed. While the clock runs the connection is idle
    (:class:`IdleConnections`).
    """

    #: Seconds a client has for its request line and headers (set by the factory).
    header_timeout_s: float = 10.0
    #: The request line and headers' limit in bytes (set by the factory).
    max_header_bytes: int = 16 * 1024
    #: The server's idle connections (one object per server, set by the factory).
    idle_connections: IdleConnections = IdleConnections(64)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._watch_headers()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._watch_headers()

    def on_response_complete(self) -> None:
        self._stop_header_timer()  # a new clock for the next request
        super().on_response_complete()
        self._watch_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_header_timer()
        self.idle_connections.busy(self)
        super().connection_lost(exc)

    def send_400_response(self, msg: str) -> None:
        """h11 could not parse the request: a JSON 400, or 431 when its headers outgrew the
        limit before they were complete; the connection is closed."""
        pending = len(self.conn.trailing_data[0])
        if pending > self.max_header_bytes:
            status, code = "431 Request Header Fields Too Large", "request_header_too_large"
            message = f"the request line and headers exceed {self.max_header_bytes} bytes"
        else:
            status, code, message = "400 Bad Request", "bad_request", "invalid HTTP request"
        if not self.transport.is_closing():
            self.transport.write(_json_answer(status, code, message))
            self.transport.close()

    def _awaiting_request(self) -> bool:
        """No request in the app: the client is (or should be) sending the next one."""
        return self.cycle is None or self.cycle.response_complete

    def _watch_headers(self) -> None:
        if self.transport.is_closing() or not self._awaiting_request():
            self._stop_header_timer()
            self.idle_connections.busy(self)
        elif self._header_timer is None:
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)
            self.idle_connections.idle(self)

    def _stop_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        if self.transport.is_closing() or not self._awaiting_request():
            return
        log.info(
            "client %s did not send its request headers within %g s: 408, connection closed",
            _peer(self.client),
            self.header_timeout_s,
        )
        if self.conn.our_state is h11.IDLE:  # nothing answered on this request yet
            self.transport.write(_timeout_answer(self.header_timeout_s))
        self.transport.close()


def guarded_protocol(
    header_timeout_s: float, max_idle_connections: int, max_header_bytes: int
) -> type[GuardedH11]:
    """:class:`GuardedH11` with these limits and an idle-connection registry of its own
    (uvicorn builds one protocol object per connection from the class: one class per server)."""
    return type(
        "GuardedH11",
        (GuardedH11,),
        {
            "header_timeout_s": header_timeout_s,
            "max_header_bytes": max_header_bytes,
            "idle_connections": IdleConnections(max_idle_connections),
        },
    )


def _timeout_answer(timeout_s: float) -> bytes:
    return _json_answer(
        "408 Request Timeout",
        "request_timeout",
        f"the request headers did not arrive within {timeout_s:g} s",
    )


def _json_answer(status: str, code: str, message: str) -> bytes:
    """A whole HTTP/1.1 answer with the API's JSON error that closes the connection."""
    body = json.dumps(error_body(code, message)).encode()
    head = (
        f"HTTP/1.1 {status}\r\ncontent-type: application/json\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    )
    return head.encode() + body


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "?"
