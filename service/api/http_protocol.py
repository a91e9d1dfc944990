"""uvicorn's h11 protocol with a deadline on the request line and headers (slowloris).

uvicorn times out a connection only while it is idle between two requests (``timeout_keep_alive``): a connection
that never sends a byte, or that sends its headers a line at a time, stays open for good, and a few thousand of
them hold every file descriptor the process may open. Here:

- a new connection that sends nothing is closed after the keep-alive timeout, as an idle one between requests is;
- once a request's first bytes arrive, its request line and headers are due within ``header_timeout_s``; then the
  connection gets a JSON 408 and is closed (nginx's ``client_header_timeout``, Apache's ``mod_reqtimeout``), counted in
  ``mfgnet_http_header_timeouts_total`` and written as an access line (status 408, the peer's address). Written
  below the ASGI layer, the 408 carries the hardening headers of ``security_headers.py`` itself.

Bodies have their own limits (``body_timeout_s``, ``body_min_rate``: ``middleware.py``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import uuid

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.api.metrics import Metrics
from service.api.security_headers import CSP, HEADERS, NOTHING_ALLOWED
from service.core.logging import ACCESS_LOGGER

access_log = logging.getLogger(ACCESS_LOGGER)


class HeaderTimeoutH11Protocol(H11Protocol):
    header_timeout_s: float = 15.0  # set by :func:`h11_protocol`
    metrics: Metrics | None = None  # the app's, for mfgnet_http_header_timeouts_total (set by :func:`h11_protocol`)
    _header_timer: asyncio.TimerHandle | None = None
    _first_byte_at: float = 0.0  # loop time of the pending request's first byte

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        # Nothing sent yet: idle, as between two requests (uvicorn cancels this timer when data arrives).
        self.timeout_keep_alive_task = self.loop.call_later(self.timeout_keep_alive, self.timeout_keep_alive_handler)

    def data_received(self, data: bytes) -> None:
        if self._header_timer is None and self.conn.their_state is h11.IDLE:  # a request's first bytes
            self._first_byte_at = self.loop.time()
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:  # its headers are complete (or it was refused)
            self._cancel_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_timer()
        super().connection_lost(exc)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self) -> None:
        self._header_timer = None
        if self.conn.their_state is not h11.IDLE or self.transport.is_closing():
            return
        message = f"the request headers did not arrive within {self.header_timeout_s:g} s (header_timeout_s)"
        body = json.dumps({"error": message}).encode()
        request_id = uuid.uuid4().hex  # as the request context's for a request without a usable X-Request-ID
        hardening = b"".join(b"%s: %s\r\n" % pair for pair in (*HEADERS, (CSP, NOTHING_ALLOWED.encode())))
        self.transport.write(  # h11 sends no response before a request: the bytes are written as they are
            b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\ncontent-length: %d\r\n"
            b"x-request-id: %s\r\n%sconnection: close\r\n\r\n%s" % (len(body), request_id.encode(), hardening, body)
        )
        self.transport.close()
        if self.metrics is not None:
            self.metrics.header_timeouts.inc()
        # The access line of the request context (middleware.py) but for the request line, which may not have
        # arrived whole: no method, route or path, and the peer's address (no proxy's X-Forwarded-For was read).
        access_log.info("request", extra={
            "request_id": request_id,
            "status": 408,
            "ms": round(1000 * (self.loop.time() - self._first_byte_at), 2),
            "bytes_in": 0,
            "client": self.client[0] if self.client else "",
            "error": message,
        })


def h11_protocol(header_timeout_s: float, metrics: Metrics | None = None) -> type[HeaderTimeoutH11Protocol]:
    """The protocol class for ``uvicorn.run(http=...)`` with this header deadline, counting its 408s in ``metrics``."""
    return type("HeaderTimeoutH11Protocol", (HeaderTimeoutH11Protocol,),
                {"header_timeout_s": header_timeout_s, "metrics": metrics})
