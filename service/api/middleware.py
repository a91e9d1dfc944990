"""The outermost layer of every request: request id, body-size limit, metrics, one JSON log line,
and the last-resort JSON 500 (with the traceback in the server log only)."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import time
import uuid
from urllib.parse import unquote

from starlette.requests import ClientDisconnect
from starlette.routing import Match, Mount, Route, compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.cors import with_cors
from service.api.errors import BodyTimeoutError, BodyTooLargeError, BodyTooSlowError, shortened
from service.api.metrics import Metrics
from service.api.server_options import SERVER_ROUTE
from service.core.logging import ACCESS_LOGGER, APP_LOGGER

access_log = logging.getLogger(ACCESS_LOGGER)
app_log = logging.getLogger(APP_LOGGER)

REQUEST_ID_HEADER = "x-request-id"
_SAFE_ID = re.compile(r"^[A-Za-z0-9._:\-]{1,128}$")
UNMATCHED_ROUTE = "<unmatched>"
# The methods the metrics name; any other a client sends counts as OTHER_METHOD (each new label is a new series: 20,000
# made-up methods grew /metrics from 54 KB to 4 MB).
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH", "TRACE", "CONNECT"})
OTHER_METHOD = "other"
MAX_ERROR_BODY_BYTES = 4096  # of an error response, read back for the access line's ``error``
# ``scope["state"]`` key of ``(status, message)`` where the HTTP protocol answered a request whose body it could not
# parse (``http_protocol.py``); the app sees a disconnect
ANSWERED_BELOW = "mfgnet.answered_below"
# ``scope["state"]`` keys: the connection's ``transport.abort`` (set by ``http_protocol.py``: an answer that gives up on
# its client closes the connection at once, its unsent bytes dropped, rather than leaving it open until they drain),
# and a flag set by an answer that gave up on a client that read none of it, or by the protocol where the connection
# was lost before the answer went out whole (logged and counted as 499)
ABORT_CONNECTION = "mfgnet.abort_connection"
DROPPED_CLIENT = "mfgnet.dropped_client"
# ``scope["state"]`` key of the start of a HEAD error's body, which ``head.py`` drops before this layer sees it
HEAD_ERROR_BODY = "mfgnet.head_error_body"
# A request still running when the shutdown grace ends is cancelled: its answer (a 503 the client may send again)
SHUTDOWN_MESSAGE = ("the server is shutting down and the request did not finish within its grace; send it again (to "
                    "another replica or once the server is back)")


def request_id_of(scope: Scope) -> str:
    """The request's ``X-Request-ID`` where it is usable, else a new one."""
    for key, value in scope.get("headers", []):
        if key == b"x-request-id":
            text = value.decode("latin-1").strip()
            if _SAFE_ID.match(text):
                return text
    return uuid.uuid4().hex


def _error_message(status: int, body: bytes) -> str | None:
    """Why a request failed, for its access line: the ``"error"`` of its JSON body, cut short."""
    if status == 499:
        return "the client closed the connection before the answer"
    if status < 400:
        return None
    try:
        message = json.loads(body).get("error")
    except (ValueError, AttributeError):
        return None
    return shortened(message) if isinstance(message, str) else None


def _route_template(scope: Scope, path: str, root_path: str) -> str:
    """The route's path template; FastAPI routes set ``scope["route"]``, Starlette's plain routes and mounts
    (``/openapi.json``, the page's and the API pages' assets) do not, so they are matched here again, and a request
    answered before routing (a 413 from its ``Content-Length``) is matched against the API's path templates."""
    route = scope.get("route")
    if route is not None and getattr(route, "path", None):
        return route.path
    if path == SERVER_ROUTE.path and scope["method"] == "OPTIONS":  # OPTIONS * answered before routing (a 413)
        return SERVER_ROUTE.path
    app = scope.get("app")
    probe = {"type": "http", "path": path, "root_path": root_path, "method": scope["method"]}
    for candidate in getattr(app, "routes", ()):
        if isinstance(candidate, Route | Mount) and candidate.matches(probe)[0] is not Match.NONE:
            return candidate.path
    route_path = path[len(root_path):] if root_path and path.startswith(root_path) else path
    for template, pattern in _api_templates(app):
        if pattern.match(route_path):
            return template
    return UNMATCHED_ROUTE


def _api_templates(app: object) -> list[tuple[str, re.Pattern]]:
    """``(path template, its regex)`` of every path the app's OpenAPI description lists (FastAPI's included routers
    are no ``Route`` to match), computed once per app."""
    state = getattr(app, "state", None)
    templates = getattr(state, "route_templates", None) if state is not None else None
    if templates is None:
        openapi = getattr(app, "openapi", None)
        paths = openapi().get("paths", {}) if callable(openapi) else {}
        templates = [(template, compile_path(template)[0]) for template in paths]
        if state is not None:
            state.route_templates = templates
    return templates


def _content_length(scope: Scope) -> int | None:
    for key, value in scope.get("headers", []):
        if key == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


def _framed_twice(scope: Scope) -> bool:
    """Whether the request has both Transfer-Encoding and Content-Length: h11 frames its body by the chunked coding, a
    proxy in front may have framed it by the length (request smuggling), and the body budget counts the length. RFC
    9112 6.1: the server MUST close the connection after answering it; it is refused here."""
    names = {key for key, _ in scope.get("headers", [])}
    return b"transfer-encoding" in names and b"content-length" in names


def _scheme_folded(credentials: bytes) -> bytes:
    """An ``Authorization`` value with its scheme in lower case (RFC 9110 11.1: the scheme is case-insensitive)."""
    scheme, _, rest = credentials.partition(b" ")
    return scheme.lower() + b" " + rest.strip()


def _differing_header(scope: Scope) -> str | None:
    """``Content-Type`` or ``Authorization`` where the request has two of different values: the routes read the first,
    a proxy in front may have read the last (h11 refuses two different Content-Lengths itself); else ``None``."""
    for name, fold in ((b"content-type", bytes.lower), (b"authorization", _scheme_folded)):
        if len({fold(value.strip()) for key, value in scope.get("headers", []) if key == name}) > 1:
            return name.decode().title()
    return None


_ABSOLUTE_FORM = re.compile(rb"^https?://[^/]*", re.IGNORECASE)  # scheme and authority of an absolute-form target


def _to_origin_form(scope: Scope) -> None:
    """An absolute-form request target (``GET http://host/v2/health/live``, as sent to proxies), which a server MUST
    accept (RFC 9112 3.2.2), reduced to its path: uvicorn takes the whole target for the path (a 404). Matched on the
    target as sent (``raw_path``), its path decoded as uvicorn decodes one."""
    raw = scope.get("raw_path") or b""
    if (match := _ABSOLUTE_FORM.match(raw)) is not None:
        scope["raw_path"] = raw[match.end():] or b"/"
        scope["path"] = unquote(scope["raw_path"].decode("ascii", errors="replace"))


class RequestContextMiddleware:
    def __init__(self, app: ASGIApp, metrics: Metrics, max_body_bytes: int, max_upload_bytes: int | None = None,
                 body_timeout_s: float | None = None, body_min_rate: int | None = None,
                 cors_origins: list[str] | None = None):
        self.app = app
        self.cors_origins = cors_origins  # the app's CORS origins: its own answers get the app's CORS headers
        self.metrics = metrics
        self.max_body_bytes = max_body_bytes  # JSON and every other body
        self.max_upload_bytes = max_body_bytes if max_upload_bytes is None else max_upload_bytes  # multipart files
        self.body_timeout_s = body_timeout_s  # longest wait for the next piece of a body (None: no limit)
        self.body_min_rate = body_min_rate  # bytes/s: the whole body is due by body_timeout_s + received / rate

    def _limit(self, scope: Scope) -> tuple[int, str]:
        """The body limit for this request's content type, and the setting that holds it."""
        for key, value in scope.get("headers", ()):
            if key == b"content-type" and value.split(b";", 1)[0].strip().lower() == b"multipart/form-data":
                return self.max_upload_bytes, "MFGNET_MAX_UPLOAD_BYTES"
        return self.max_body_bytes, "MFGNET_MAX_BODY_BYTES"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        _to_origin_form(scope)
        request_id = scope.get("state", {}).get("request_id") or request_id_of(scope)  # the protocol's, if it answered
        scope.setdefault("state", {})["request_id"] = request_id
        state = {"status": 0, "started": False, "answered": False, "received": 0, "body_done": False,
                 "body_started": 0.0}
        path, root_path = scope.get("path", ""), scope.get("root_path", "")  # before routing changes them
        error_body = bytearray()  # the start of a 4xx/5xx body: its "error" goes into the access line
        limit, setting = self._limit(scope)

        counted: dict = {}  # the route, method and status the request was counted under, once counted

        def count() -> None:
            if not counted:
                counted["route"] = route = _route_template(scope, path, root_path)
                counted["method"] = method = scope["method"] if scope["method"] in KNOWN_METHODS else OTHER_METHOD
                counted["status"] = state["status"]
                self.metrics.requests.labels(route=route, method=method, status=str(state["status"])).inc()
                self.metrics.latency.labels(route=route).observe(time.perf_counter() - started)

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                state["status"], state["started"] = message["status"], True
                message["headers"] = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
            elif message["type"] == "http.response.body" and state["status"] >= 400:
                error_body.extend(message.get("body", b"")[:MAX_ERROR_BODY_BYTES - len(error_body)])
            await send(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                state["answered"] = True  # the whole answer was handed to the server
                # counted once the server took the last bytes (its send does not yield after writing them, so a scrape
                # the client sends after its answer counts it), not before: a send that stalls and is given up on
                # (MovedFileResponse's stall_s) never delivered them, a 499
                if scope["state"].get(ANSWERED_BELOW) is None and not scope["state"].get(DROPPED_CLIENT):
                    count()

        async def receive_limited() -> Message:
            if state["body_done"] or self.body_timeout_s is None:  # after the body: the wait for a disconnect
                return await receive()
            state["body_started"] = state["body_started"] or time.perf_counter()  # the route asks for it: it is due
            wait_s, stalled = self.body_timeout_s, True
            if self.body_min_rate is not None:  # the body's due time grows by a second per body_min_rate bytes
                due_s = (state["body_started"] + self.body_timeout_s + state["received"] / self.body_min_rate
                         - time.perf_counter())
                wait_s, stalled = min(wait_s, due_s), wait_s <= due_s
            try:
                if wait_s <= 0:
                    raise TimeoutError
                async with asyncio.timeout(wait_s):
                    message = await receive()
            except TimeoutError:  # a JSON 408; the route's slot is freed
                if stalled:
                    raise BodyTimeoutError(self.body_timeout_s) from None
                elapsed_s = time.perf_counter() - state["body_started"]
                raise BodyTooSlowError(state["received"], elapsed_s, self.body_min_rate) from None
            if message["type"] == "http.request":
                state["received"] += len(message.get("body", b""))
                state["body_done"] = not message.get("more_body", False)
                if state["received"] > limit:
                    raise BodyTooLargeError(limit, setting)  # turned into a JSON 413 by the error handlers
            return message

        self.metrics.in_flight.inc()
        try:
            length = _content_length(scope)
            if _framed_twice(scope):
                await self._answer(scope, receive, send_with_id, 400, "the request has both Transfer-Encoding and "
                                   "Content-Length; send one (RFC 9112 6.1)", headers=[(b"connection", b"close")])
            elif length is not None and length > limit:  # refuse before reading anything
                too_large = BodyTooLargeError(limit, setting)
                await self._answer(scope, receive, send_with_id, too_large.status, too_large.message)
            elif (differing := _differing_header(scope)) is not None:
                await self._answer(scope, receive, send_with_id, 400, f"the request has {differing} headers that "
                                                                       "differ; send one (RFC 9110 5.3)")
            else:
                await self.app(scope, receive_limited, send_with_id)
        except ClientDisconnect:
            # the client went away (nothing to answer), or an answer under way gave up on a client reading none of it
            state["status"] = 499 if scope["state"].get(DROPPED_CLIENT) else state["status"] or 499
        except asyncio.CancelledError:  # the server's shutdown grace ended with this request still running
            if state["started"]:
                raise  # too late for an answer of its own: uvicorn closes the connection
            await self._answer(scope, receive, send_with_id, 503, SHUTDOWN_MESSAGE,
                               headers=[(b"retry-after", b"1"), (b"connection", b"close")])
        except Exception:
            app_log.exception("unhandled error", extra={"request_id": request_id, "path": shortened(path)})
            if not state["started"]:
                await self._answer(scope, receive, send_with_id, 500, "internal server error", request_id=request_id)
            else:
                state["status"] = 500
        finally:
            self.metrics.in_flight.dec()
            # a HEAD answer is whole once its headers went out (HeadAsGetMiddleware serves it as a GET whose body the
            # server drops; a client that closes on the headers can cancel a file response before its last body)
            whole = scope["method"] == "HEAD" and state["started"]
            cut_short = state["started"] and not state["answered"] and state["status"] < 400  # left during a download
            if counted:  # its last body was handed to the server before a loss was seen: the line says what was counted
                state["status"] = counted["status"]
            elif not whole and (cut_short or scope["state"].get(DROPPED_CLIENT)):  # or gone before it: it went nowhere
                state["status"] = 499
            error = _error_message(state["status"], bytes(error_body or scope["state"].get(HEAD_ERROR_BODY, b"")))
            if (answered := scope["state"].get(ANSWERED_BELOW)) is not None:  # a malformed body: the protocol's 4xx
                state["status"], error = answered
            elapsed = time.perf_counter() - started
            count()  # where no last body went out: a disconnect, a 499, the protocol's own answer
            route, method = counted["route"], counted["method"]
            extra = {
                "request_id": request_id,
                "method": scope["method"] if method != OTHER_METHOD else shortened(scope["method"]),
                "route": route,
                "path": shortened(path),
                "status": state["status"],
                "ms": round(1000 * elapsed, 2),
                "bytes_in": state["received"],
                "client": shortened((scope.get("client") or ("", 0))[0]),  # (a trusted proxy's X-Forwarded-For)
            }
            if error is not None:
                extra["error"] = error
            access_log.info("request", extra=extra)

    async def _answer(self, scope: Scope, receive: Receive, send: Send, status: int, message: str,
                      headers: list[tuple[bytes, bytes]] | None = None, **extra) -> None:
        """:meth:`_send_error`, through the app's CORS middleware where CORS is on."""

        async def answer(scope: Scope, receive: Receive, send: Send) -> None:
            await self._send_error(send, status, message, headers, **extra)

        await (answer if not self.cors_origins else with_cors(answer, self.cors_origins))(scope, receive, send)

    @staticmethod
    async def _send_error(send: Send, status: int, message: str, headers: list[tuple[bytes, bytes]] | None = None,
                          **extra) -> None:
        body = json.dumps({"error": message, **extra}).encode()
        await send({
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                        *(headers or [])],
        })
        await send({"type": "http.response.body", "body": body})
