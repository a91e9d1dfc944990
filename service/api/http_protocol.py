"""uvicorn's h11 protocol with a deadline on the request line and headers (slowloris) and a cap on open connections.

uvicorn times out a connection only while it is idle between two requests (``timeout_keep_alive``): a connection
that never sends a byte, or that sends its headers a line at a time, stays open for good, and a few thousand of
them hold every file descriptor the process may open. Here:

- a new connection that sends nothing is closed after the keep-alive timeout, as an idle one between requests is;
- once a request's first bytes arrive, its request line and headers are due within ``header_timeout_s``; then the
  connection gets a JSON 408 and is closed (nginx's ``client_header_timeout``, Apache's ``mod_reqtimeout``), counted in
  ``mfgnet_http_header_timeouts_total`` and written as an access line (status 408, the peer's address). Written
  below the ASGI layer, the 408 carries the hardening headers of ``security_headers.py`` itself.

At most ``max_connections`` connections stay open (idle ones cost a file descriptor each: at a soft ``nofile`` limit
of 1024, 2,000 idle connections left the health probes unanswered). A connection beyond the cap first closes the
connection idle for longest (none sent yet, or kept alive between requests), as nginx reuses its idle connections when
its ``worker_connections`` run out: a client may always reconnect, and probes get in. Without an idle one, the
connection whose headers have been arriving for longest gets a 408 and is closed (slowloris connections, each kept for
up to ``header_timeout_s``, cannot fill the cap). Only when every open connection has a whole request is the new one
refused: a JSON 503 with ``Retry-After`` at once, its write side shut and the
socket closed a second later (so the answer is read, not reset), counted in ``mfgnet_http_connections_refused_total``.
uvicorn's own ``limit_concurrency`` reads the request first, answers a plain-text 503, and leaves idle connections open.

A request answered before its body was read whole (a 413 from its Content-Length, a 415, a 503 from a full queue, a
408 for a stalled body) leaves the rest of its body to come: uvicorn read it for as long as it kept coming, with no
timer at all, so a byte now and then held the connection for good. Here it is read (and dropped) for at most
``LINGER_MAX_S``, and the connection closed once none has come for ``LINGER_IDLE_S`` (nginx's ``lingering_time`` and
``lingering_timeout``); a body that ends in time leaves the connection to serve its next request. A lingering
connection, its answer sent, is the first to go when the cap needs room after the idle ones.

A request h11 cannot parse (a bad request line, an invalid header name, a Content-Length that is not a number, a
malformed chunk of a chunked body) got uvicorn's plain-text ``400 Invalid HTTP request received.``; here it gets a JSON
answer naming h11's complaint without the bytes it quotes (a header line may hold the API key), with the status h11
suggests where it is a 4xx (431 for a request line and headers over ``h11_max_incomplete_event_size``, 16 KiB; 400
otherwise, where h11 suggests 501 for a transfer coding other than chunked too), the hardening headers,
``connection: close`` and an access line. An error in a body whose request reached the app takes
that request's id and access line (``middleware.ANSWERED_BELOW``); one in the rest of a body already answered closes
the connection. The write side is shut and what the client still sends is dropped for ``REFUSED_LINGER_S`` before the
socket closes, so the answer is read rather than reset away (1 MB of headers).

Bodies have their own limits (``body_timeout_s``, ``body_min_rate``: ``middleware.py``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import sys
import uuid
from collections import OrderedDict
from typing import ClassVar

import h11
from h11._connection import DEFAULT_MAX_INCOMPLETE_EVENT_SIZE  # as uvicorn's h11_impl imports it
from uvicorn.protocols.http.h11_impl import STATUS_PHRASES, H11Protocol

from service.api.metrics import Metrics
from service.api.middleware import ABORT_CONNECTION, ANSWERED_BELOW, DROPPED_CLIENT, request_id_of
from service.api.security_headers import CSP, HEADERS, NOTHING_ALLOWED
from service.core.logging import ACCESS_LOGGER, APP_LOGGER

access_log = logging.getLogger(ACCESS_LOGGER)
FD_RESERVE = 100  # file descriptors kept for other than connections: models, spooled uploads, logs, the loop's own
REFUSED_LINGER_S = 1.0  # a refused connection's socket stays open this long after its 503, so the client reads it
RETRY_AFTER_REFUSED_S = 1
LINGER_IDLE_S = 5.0  # the rest of an answered request's body: closed once none has come for this long...
LINGER_MAX_S = 30.0  # ...or this long after the answer, whatever comes
MAX_DETAIL_CHARS = 200  # of h11's complaint
_QUOTED = re.compile(r":? (?=bytearray\(|b['\"])")  # where h11's complaint starts quoting the request's bytes
_HEAD_END = re.compile(rb"\n\r?\n")  # the blank line that ends the headers, as h11 finds it
ROOM_MESSAGE = ("the request headers were still arriving when a new connection needed the place "
                "(MFGNET_MAX_CONNECTIONS); send them at once")


class HeaderTimeoutH11Protocol(H11Protocol):
    header_timeout_s: float = 15.0  # set by :func:`h11_protocol`
    metrics: Metrics | None = None  # the app's, for mfgnet_http_header_timeouts_total (set by :func:`h11_protocol`)
    _header_timer: asyncio.TimerHandle | None = None
    _first_byte_at: float = 0.0  # loop time of the pending request's first byte
    max_connections: int | None = None  # open connections at most (set by :func:`h11_protocol`)
    # This server's idle connections, longest idle first (:func:`h11_protocol` gives each server its own).
    idle: ClassVar[OrderedDict[HeaderTimeoutH11Protocol, None]] = OrderedDict()
    # Its connections whose request headers are arriving, the earliest first byte first.
    arriving: ClassVar[OrderedDict[HeaderTimeoutH11Protocol, None]] = OrderedDict()
    # Its connections answered before their request's body was read whole, discarding the rest, the earliest first.
    lingering: ClassVar[OrderedDict[HeaderTimeoutH11Protocol, None]] = OrderedDict()
    _refused: bool = False
    _dropping: bool = False  # closing after its answer: the rest of the body is dropped until the linger timers end
    _shutting_down: bool = False
    _linger_timer: asyncio.TimerHandle | None = None
    _linger_until: float = 0.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if self.max_connections is not None and len(self.connections) > self.max_connections and not self._make_room():
            self._refuse()
            return
        # Nothing sent yet: idle, as between two requests (uvicorn cancels this timer when data arrives).
        self.timeout_keep_alive_task = self.loop.call_later(self.timeout_keep_alive, self.timeout_keep_alive_handler)
        self.idle[self] = None

    def _make_room(self) -> bool:
        """Close the connection idle for longest (as its keep-alive timeout would), else the one whose headers have
        been arriving for longest (a 408, as its header deadline would; slowloris connections cannot fill the cap);
        ``False`` if every other connection has a whole request."""
        for other in self.idle:
            if not other.transport.is_closing():
                other._unset_keepalive_if_required()
                other.timeout_keep_alive_handler()
                return True
        for other in self.lingering:
            if not other.transport.is_closing():
                other._stop_lingering()
                return True
        for other in self.arriving:
            if other is not self and not other.transport.is_closing():
                other._headers_late(ROOM_MESSAGE)
                return True
        return False

    def _refuse(self) -> None:
        """A JSON 503 before any request, the write side shut; the socket is closed after ``REFUSED_LINGER_S``."""
        self._refused = True
        message = (f"the server has {self.max_connections} connections open, each busy with a request "
                   "(MFGNET_MAX_CONNECTIONS); retry later")
        body = json.dumps({"error": message}).encode()
        self.transport.write(
            b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\ncontent-length: %d\r\n"
            b"retry-after: %d\r\n%sconnection: close\r\n\r\n%s"
            % (len(body), RETRY_AFTER_REFUSED_S, _hardening(), body)
        )
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(REFUSED_LINGER_S, self.transport.close)
        if self.metrics is not None:
            self.metrics.connections_refused.inc()

    def _unset_keepalive_if_required(self) -> None:
        super()._unset_keepalive_if_required()
        self.idle.pop(self, None)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if self.conn.their_state is h11.SEND_BODY and not self.transport.is_closing():  # answered, its body unread
            self._unset_keepalive_if_required()
            if self._linger_timer is None:  # (a closing answer's lingering, _LingeringClose, started already)
                self._start_lingering()
            return
        if self.timeout_keep_alive_task is not None:  # idle again, until the next request's first bytes
            self.idle[self] = None
            self.idle.move_to_end(self)

    def _start_lingering(self) -> None:
        """Drop the rest of an answered body for at most ``LINGER_MAX_S``, closing once none came for ``LINGER_IDLE_S``
        (once the server shuts down: ``REFUSED_LINGER_S``, within its grace)."""
        idle_s = REFUSED_LINGER_S if self._shutting_down else LINGER_IDLE_S
        self._linger_until = self.loop.time() + (REFUSED_LINGER_S if self._shutting_down else LINGER_MAX_S)
        self._linger_timer = self.loop.call_later(idle_s, self._stop_lingering)
        self.lingering[self] = None

    def _linger_on(self) -> None:
        """More of a lingering body came: close once none comes for ``LINGER_IDLE_S``, by ``_linger_until`` at the
        latest."""
        left = self._linger_until - self.loop.time()
        self._linger_timer = self.loop.call_later(max(0.0, min(LINGER_IDLE_S, left)), self._stop_lingering)

    def shutdown(self) -> None:
        self._shutting_down = True
        super().shutdown()

    def data_received(self, data: bytes) -> None:
        if self._refused:  # answered already: what it sends is not read
            if self._dropping and self._linger_timer is not None:  # the rest of a closing answer's body: still coming
                self._linger_timer.cancel()
                self._linger_on()
            return
        if self._linger_timer is not None:  # the rest of an answered request's body, read (and dropped) by uvicorn
            self._linger_timer.cancel()
            self._linger_timer = None
            answered = self.cycle
            super().data_received(data)
            if self.cycle is answered and self.conn.their_state is h11.SEND_BODY:  # more of it to come
                self._linger_on()
                return
            self.lingering.pop(self, None)  # its body ended: the connection serves its next request as any other
            if self.cycle is answered and not self.transport.is_closing():
                if self.conn.their_state is h11.IDLE and self.conn.trailing_data[0]:  # the next request's first bytes
                    self._first_byte_at = self.loop.time()
                    self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)
                    self.arriving[self] = None
                elif self.conn.their_state is h11.IDLE:  # idle, as after any answer
                    self.timeout_keep_alive_task = self.loop.call_later(self.timeout_keep_alive,
                                                                        self.timeout_keep_alive_handler)
                    self.idle[self] = None
            return
        if self._header_timer is None and self.conn.their_state is h11.IDLE:  # a request's first bytes
            self._first_byte_at = self.loop.time()
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._headers_late)
            self.arriving[self] = None
        if self.conn.their_state is h11.IDLE:
            data = self._head_within_limit(data)
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:  # its headers are complete (or it was refused)
            self._cancel_header_timer()

    def _should_upgrade(self) -> bool:
        """Never: the service has no WebSocket route. uvicorn handed a WebSocket upgrade to its WebSocket protocol
        (wsproto is installed), which answered a bare 403 (no JSON, hardening headers, X-Request-ID or access line), and
        logged a warning per other upgrade (h2c); the request is served as the HTTP request it also is."""
        return False

    def handle_events(self) -> None:
        super().handle_events()
        if self.cycle is not None:  # an answer that gives up on its client can close the connection at once
            self.cycle.scope.setdefault("state", {}).setdefault(ABORT_CONNECTION, self.transport.abort)
            if not isinstance(self.cycle.transport, _LingeringClose):
                self.cycle.transport = _LingeringClose(self)  # type: ignore[assignment]

    def _head_within_limit(self, data: bytes) -> bytes:
        """``data``, or where the request line and headers run on past ``h11_max_incomplete_event_size``, the part of it
        that takes h11's buffer one byte past the limit. h11 checks the limit only while the headers are incomplete,
        so headers that arrived whole in one read passed at any size; cut, they get the 431 of headers sent in parts."""
        limit = self.config.h11_max_incomplete_event_size or DEFAULT_MAX_INCOMPLETE_EVENT_SIZE
        buffered = self.conn.trailing_data[0]
        if len(buffered) + len(data) <= limit:
            return data
        head = buffered + data[:limit + 1 - len(buffered)]  # [limit + 1] bytes
        return data if _HEAD_END.search(head) else data[:limit + 1 - len(buffered)]

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to a request h11 cannot parse, called while h11's ``RemoteProtocolError`` is handled: a
        JSON 4xx naming it (the status h11 suggests where it is a 4xx, else 400), the hardening headers, an access line;
        the write side shut, the socket closed after ``REFUSED_LINGER_S``."""
        if self.conn.our_state not in (h11.IDLE, h11.SEND_RESPONSE):  # answered already (its body's rest was bad)
            self.transport.close()
            return
        cycle = self.cycle if self.cycle is not None and not self.cycle.response_complete else None  # in its body
        error = sys.exc_info()[1]
        status = getattr(error, "error_status_hint", 400)
        status = status if 400 <= status < 500 else 400  # 501 for a transfer coding other than chunked: the client's
        limit = self.config.h11_max_incomplete_event_size or DEFAULT_MAX_INCOMPLETE_EVENT_SIZE
        if status == 431 and cycle is None:  # no end of the headers within the limit
            message = f"the request line and headers are over {limit} bytes; send smaller headers"
        elif status == 431:  # a chunk-size line of the body
            status, message = 400, f"invalid HTTP request: a line of the chunked body is over {limit} bytes"
        else:
            detail = str(error) if isinstance(error, h11.RemoteProtocolError) else msg
            # without the bytes h11 quotes: a header line may hold the API key (neither answered nor logged)
            detail = _QUOTED.split(detail, maxsplit=1)[0][:MAX_DETAIL_CHARS]
            message = f"invalid HTTP request: {detail}"
        state = cycle.scope.setdefault("state", {}) if cycle is not None else {}
        # the request context's (the app may not have started yet: it takes this one then)
        request_id = state.setdefault("request_id", request_id_of(cycle.scope)) if cycle else uuid.uuid4().hex
        body = json.dumps({"error": message}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", b"%d" % len(body)),
                   (b"x-request-id", request_id.encode()), *_hardening_pairs(), (b"connection", b"close")]
        self.transport.write(self.conn.send(h11.Response(status_code=status, headers=headers,
                                                         reason=STATUS_PHRASES[status])))
        self.transport.write(self.conn.send(h11.Data(data=body)))
        self.transport.write(self.conn.send(h11.EndOfMessage()))
        self._refused = True  # what it sends now is dropped
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(REFUSED_LINGER_S, self.transport.close)
        self.lingering[self] = None  # the cap may close it first
        if cycle is not None:  # the app reading its body: a disconnect; the request context writes the access line
            state[ANSWERED_BELOW] = (status, message)
            cycle.disconnected = True
            cycle.message_event.set()
            return
        access_log.info("request", extra={  # as the 408's: the request line may not have been read
            "request_id": request_id,
            "status": status,
            "ms": round(1000 * (self.loop.time() - self._first_byte_at), 2) if self._first_byte_at else 0.0,
            "bytes_in": 0,
            "client": self.client[0] if self.client else "",
            "error": message,
        })

    def _stop_lingering(self) -> None:
        self.lingering.pop(self, None)
        if self._linger_timer is not None:
            self._linger_timer.cancel()
            self._linger_timer = None
        self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.cycle is not None and not self.cycle.response_complete:  # its answer goes nowhere: a 499
            self.cycle.scope.setdefault("state", {})[DROPPED_CLIENT] = True
        self._cancel_header_timer()
        self.idle.pop(self, None)
        self.lingering.pop(self, None)
        if self._linger_timer is not None:
            self._linger_timer.cancel()
            self._linger_timer = None
        super().connection_lost(exc)

    def _cancel_header_timer(self) -> None:
        self.arriving.pop(self, None)
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _headers_late(self, message: str | None = None) -> None:
        """The 408 for headers not whole after ``header_timeout_s`` (counted), or closed early with ``message``."""
        late = message is None
        self._cancel_header_timer()
        if self.conn.their_state is not h11.IDLE or self.transport.is_closing():
            return
        if late:
            message = f"the request headers did not arrive within {self.header_timeout_s:g} s (MFGNET_HEADER_TIMEOUT_S)"
        body = json.dumps({"error": message}).encode()
        request_id = uuid.uuid4().hex  # as the request context's for a request without a usable X-Request-ID
        self.transport.write(  # h11 sends no response before a request: the bytes are written as they are
            b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\ncontent-length: %d\r\n"
            b"x-request-id: %s\r\n%sconnection: close\r\n\r\n%s" % (len(body), request_id.encode(), _hardening(), body)
        )
        self.transport.close()
        if late and self.metrics is not None:
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


class _LingeringClose:
    """The transport as a request cycle sees it: where uvicorn closes the connection after an answer (the request
    said ``Connection: close``) while the request's body is still arriving, the write side is shut and the rest of the
    body dropped as a kept-alive answer's rest is (``LINGER_IDLE_S`` idle, ``LINGER_MAX_S`` at most; a client on a
    slow link still sending reads the answer once it has sent its body), so the client reads the answer (a
    413/415/503) instead of a reset."""

    def __init__(self, protocol: HeaderTimeoutH11Protocol):
        self._protocol = protocol

    def __getattr__(self, name: str):
        return getattr(self._protocol.transport, name)

    def close(self) -> None:
        protocol, transport = self._protocol, self._protocol.transport
        if protocol.conn.their_state is h11.SEND_BODY and not transport.is_closing() and transport.can_write_eof():
            protocol._refused = protocol._dropping = True  # what it still sends is read and dropped
            transport.write_eof()
            protocol._unset_keepalive_if_required()
            if protocol._linger_timer is None:
                protocol._start_lingering()  # as a kept-alive answer's rest: LINGER_IDLE_S idle, LINGER_MAX_S at most
            return
        transport.close()


UVICORN_BACKLOG = 2048  # uvicorn's listen backlog; asyncio accepts up to this many connections before any is handled


def connection_limits(max_connections: int) -> tuple[int, int]:
    """``(cap on open connections, listen backlog)``: ``max_connections`` and uvicorn's backlog, or less where the
    open-file limit would run out first. The soft ``nofile`` limit is raised to the hard one first (as nginx's
    ``worker_rlimit_nofile`` and Go programs do; containers often start at a soft 1024). asyncio accepts up to a
    backlog of connections at once before any of them is handled (and so before the cap can close one), so the cap,
    the backlog and :data:`FD_RESERVE` must fit in the limit together; a log line says when they were lowered. Past
    the limit, ``accept()`` fails: new connections wait unanswered, probes included, and asyncio logs the failure
    thousands of times a second."""
    try:
        import resource
    except ImportError:  # not a Unix: no such limit to read
        return max_connections, UVICORN_BACKLOG
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != hard:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError):  # e.g. an unlimited hard limit, above the kernel's nr_open: keep the soft one
            pass
    if soft == resource.RLIM_INFINITY or max_connections + UVICORN_BACKLOG + FD_RESERVE <= soft:
        return max_connections, UVICORN_BACKLOG
    room = max(2, soft - FD_RESERVE)
    backlog = min(UVICORN_BACKLOG, room // 2)
    cap = max(1, min(max_connections, room - backlog))
    logging.getLogger(APP_LOGGER).warning(
        "MFGNET_MAX_CONNECTIONS and the listen backlog lowered to fit the open-file limit (nofile)",
        extra={"max_connections": max_connections, "nofile": soft, "cap": cap, "backlog": backlog},
    )
    return cap, backlog


def _hardening_pairs() -> tuple[tuple[bytes, bytes], ...]:
    """The headers of ``security_headers.py`` (for the answers written below the ASGI layer)."""
    return (*HEADERS, (CSP, NOTHING_ALLOWED.encode()))


def _hardening() -> bytes:
    """:func:`_hardening_pairs` as header lines."""
    return b"".join(b"%s: %s\r\n" % pair for pair in _hardening_pairs())


def h11_protocol(header_timeout_s: float, metrics: Metrics | None = None,
                 max_connections: int | None = None) -> type[HeaderTimeoutH11Protocol]:
    """The protocol class for ``uvicorn.run(http=...)`` with this header deadline and connection cap (``None``: no
    cap), counting its 408s and refused connections in ``metrics``; one class per server (it holds the idle ones)."""
    return type("HeaderTimeoutH11Protocol", (HeaderTimeoutH11Protocol,),
                {"header_timeout_s": header_timeout_s, "metrics": metrics, "max_connections": max_connections,
                 "idle": OrderedDict(), "arriving": OrderedDict(), "lingering": OrderedDict()})
