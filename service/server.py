"""uvicorn as ``hmpf-serve`` runs it: its options from the settings, and a connection protocol
that gives a client a deadline for its request headers.

What bounds a client (the settings, :class:`~service.settings.Settings`):

* ``header_timeout_s``: from the connection (or the end of the previous answer on a kept-alive
  connection) to the end of the request's headers; a client that is later gets a 408 and the
  connection is closed (:class:`HeaderDeadlineH11`; uvicorn has no such timeout: a client that
  opens a connection and sends nothing would keep it for ever). No request reached the app,
  so ``hmpf_requests_total`` does not count it; the log has one line.
* ``body_timeout_s``: the body, once the headers are in (:class:`~service.limits.BodyDeadline`,
  a 408 JSON error).
* ``max_connections``: connections open at once; a request on one more is answered 503 by
  uvicorn (``limit_concurrency``).
* ``keep_alive_s``: an idle kept-alive connection is closed after it (``timeout_keep_alive``).
* ``max_header_bytes``: the request line and headers (h11's incomplete event size); more is a
  400 from uvicorn.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import TYPE_CHECKING, Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.errors import error_body

if TYPE_CHECKING:
    from fastapi import FastAPI

    from service.settings import Settings

__all__ = ["HeaderDeadlineH11", "uvicorn_config"]

log = logging.getLogger("hmpf.service")
#: The graceful shutdown's limit (s): requests in flight get this long to finish.
GRACEFUL_SHUTDOWN_S = 10


def uvicorn_config(app: FastAPI, settings: Settings) -> uvicorn.Config:
    """The uvicorn options of ``hmpf-serve``, from ``settings``."""
    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
        http=header_deadline_protocol(settings.header_timeout_s),
        # uvicorn counts the connection the request came on: n + 1 serves n connections.
        limit_concurrency=settings.max_connections + 1,
        timeout_keep_alive=settings.keep_alive_s,
        h11_max_incomplete_event_size=settings.max_header_bytes,
    )


class HeaderDeadlineH11(H11Protocol):
    """uvicorn's h11 protocol with a deadline for the request headers.

    The clock starts when the connection opens, and again when an answer has been sent on a
    kept-alive connection; it stops when a request's headers are complete (the app has it,
    and :class:`~service.limits.BodyDeadline` times its body). A client that misses it gets a
    408 and the connection is closed.
    """

    #: Seconds a client has for its request line and headers (set by the factory).
    header_timeout_s: float = 10.0

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
        super().connection_lost(exc)

    def _awaiting_request(self) -> bool:
        """No request in the app: the client is (or should be) sending the next one."""
        return self.cycle is None or self.cycle.response_complete

    def _watch_headers(self) -> None:
        if self.transport.is_closing() or not self._awaiting_request():
            self._stop_header_timer()
        elif self._header_timer is None:
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)

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


def header_deadline_protocol(timeout_s: float) -> type[HeaderDeadlineH11]:
    """:class:`HeaderDeadlineH11` with a deadline of ``timeout_s`` (uvicorn builds one
    protocol object per connection from the class)."""
    return type("HeaderDeadlineH11", (HeaderDeadlineH11,), {"header_timeout_s": timeout_s})


def _timeout_answer(timeout_s: float) -> bytes:
    body = json.dumps(
        error_body("request_timeout", f"the request headers did not arrive within {timeout_s:g} s")
    ).encode()
    head = (
        "HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    )
    return head.encode() + body


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "?"
