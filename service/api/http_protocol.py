"""uvicorn's h11 protocol with a deadline on the request line and headers (slowloris).

uvicorn times out a connection only while it is idle between two requests (``timeout_keep_alive``): a connection
that never sends a byte, or that sends its headers a line at a time, stays open for good, and a few thousand of
them hold every file descriptor the process may open. Here:

- a new connection that sends nothing is closed after the keep-alive timeout, as an idle one between requests is;
- once a request's first bytes arrive, its request line and headers are due within ``header_timeout_s``; then the
  connection gets a JSON 408 and is closed (nginx's ``client_header_timeout``, Apache's ``mod_reqtimeout``).

Bodies have their own limits (``body_timeout_s``, ``body_min_rate``: ``middleware.py``).
"""

from __future__ import annotations

import asyncio
import json
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.core.logging import APP_LOGGER

log = logging.getLogger(APP_LOGGER)


class HeaderTimeoutH11Protocol(H11Protocol):
    header_timeout_s: float = 15.0  # set by :func:`h11_protocol`
    _header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        # Nothing sent yet: idle, as between two requests (uvicorn cancels this timer when data arrives).
        self.timeout_keep_alive_task = self.loop.call_later(self.timeout_keep_alive, self.timeout_keep_alive_handler)

    def data_received(self, data: bytes) -> None:
        if self._header_timer is None and self.conn.their_state is h11.IDLE:  # a request's first bytes
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
        self.transport.write(  # h11 sends no response before a request: the bytes are written as they are
            b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\n"
            b"content-length: %d\r\nconnection: close\r\n\r\n%s" % (len(body), body)
        )
        self.transport.close()
        log.warning("request headers timed out; connection closed",
                    extra={"client": self.client[0] if self.client else "", "header_timeout_s": self.header_timeout_s})


def h11_protocol(header_timeout_s: float) -> type[HeaderTimeoutH11Protocol]:
    """The protocol class for ``uvicorn.run(http=...)`` with this header deadline."""
    return type("HeaderTimeoutH11Protocol", (HeaderTimeoutH11Protocol,), {"header_timeout_s": header_timeout_s})
