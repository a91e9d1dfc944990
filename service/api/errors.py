"""Every error is JSON ``{"error": "<what is wrong>"}`` (sometimes with ``detail``) and the right status.

Routes raise :class:`APIError` (or a subclass); the handlers below turn it, validation errors,
pipeline ``InputError`` and unknown routes into JSON. Bodies never carry tracebacks, file paths or
the submitted points.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from service.api.schemas import ErrorResponse
from service.core.logging import APP_LOGGER
from service.registrar import InputError

log = logging.getLogger(APP_LOGGER)

MAX_LISTED_ERRORS = 5  # in the "error" sentence
MAX_DETAIL_ERRORS = 20  # in "detail"


class APIError(Exception):
    """An expected failure with its HTTP status and a message safe to show to the client."""

    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None, **extra: Any):
        super().__init__(message)
        self.status = status
        self.message = message
        self.headers = headers or {}
        self.extra = extra


class BodyTooLargeError(APIError):
    def __init__(self, limit: int, setting: str = "MFGNET_MAX_BODY_BYTES"):
        super().__init__(413, f"request body is larger than the limit of {limit} bytes ({setting})")


class BodyTimeoutError(APIError):
    def __init__(self, timeout_s: float):
        super().__init__(408, f"the request body stalled: no data for {timeout_s:g} s (MFGNET_BODY_TIMEOUT_S)",
                         headers={"Connection": "close"})


class BodyTooSlowError(APIError):
    def __init__(self, received: int, elapsed_s: float, min_rate: int):
        super().__init__(408, f"the request body arrived too slowly: {received} bytes in {elapsed_s:.0f} s, below "
                         f"{min_rate} bytes/s after the first MFGNET_BODY_TIMEOUT_S (MFGNET_BODY_MIN_RATE)",
                         headers={"Connection": "close"})


class TempStorageError(APIError):
    """The server's temporary folder (``TMPDIR``, else ``/tmp``: uploads past 1 MiB and aligned answers are written
    there) is full or not writable: a 503 to retry, not a 500."""

    def __init__(self, exc: OSError, what: str):
        super().__init__(503, f"the server could not write {what} to its temporary folder ({exc.strerror or exc}): it "
                              "is full or not writable; retry later", headers={"Retry-After": "5"})


def error_response(status: int, message: str, headers: dict[str, str] | None = None, **extra: Any) -> JSONResponse:
    return JSONResponse({"error": message, **extra}, status_code=status, headers=headers)


def format_loc(loc: Sequence[Any]) -> str:
    """``("body", "source", 5, 1)`` -> ``"source[5][1]"``."""
    out = ""
    for part in loc:
        if part == "body" and not out:
            continue
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "body"


def validation_error(errors: Sequence[dict], prefix: str = "") -> APIError:
    """Pydantic errors -> 422 naming each field and its problem (inputs are never echoed)."""
    items = [
        {"loc": (prefix + "." if prefix else "") + format_loc(e.get("loc", ())), "msg": e.get("msg", "invalid")}
        for e in errors
    ]
    listed = "; ".join(f"{i['loc']}: {i['msg']}" for i in items[:MAX_LISTED_ERRORS])
    more = f" (and {len(items) - MAX_LISTED_ERRORS} more)" if len(items) > MAX_LISTED_ERRORS else ""
    return APIError(422, f"invalid request: {listed}{more}", detail=items[:MAX_DETAIL_ERRORS])


def from_pydantic(exc: ValidationError, prefix: str = "") -> APIError:
    return validation_error(exc.errors(include_url=False, include_input=False, include_context=False), prefix)


async def _api_error(request: Request, exc: APIError) -> JSONResponse:
    return error_response(exc.status, exc.message, exc.headers, **exc.extra)


async def _input_error(request: Request, exc: InputError) -> JSONResponse:
    return error_response(422, str(exc))


async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
    err = validation_error(list(exc.errors()))
    return error_response(err.status, err.message, **err.extra)


# A request's path or method in a log line or an error message is cut to this many characters: uvicorn takes request
# lines of over 100 KB, and each made a log line (and a 404 body) of that size. The access line's ``error`` too.
MAX_LOGGED_CHARS = 256


def shortened(text: str) -> str:
    """``text`` cut to :data:`MAX_LOGGED_CHARS` characters (``...`` marks a cut)."""
    return text if len(text) <= MAX_LOGGED_CHARS else text[:MAX_LOGGED_CHARS] + "..."


# ``scope["state"]`` key set by ``head.py``: the request is a HEAD served as its GET (its messages name HEAD)
HEAD_REQUEST = "mfgnet.head_request"


async def _http_exception(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    method = "HEAD" if request.scope.get("state", {}).get(HEAD_REQUEST) else request.method
    method, path = shortened(method), shortened(request.scope.get("path") or request.url.path)  # as the access line
    if exc.status_code == 404:
        message = f"not found: {method} {path}{_slash_hint(request)}"
    elif exc.status_code == 405:
        message = f"method {method} not allowed on {path}"
    else:
        message = str(exc.detail)
    return error_response(exc.status_code, message, dict(exc.headers or {}))


def _slash_hint(request: Request) -> str:
    """Where a path with a trailing slash names a route without it: the server does not redirect (a 307 made clients
    send a POST's body twice, to a Location built from the Host and scheme it saw)."""
    path = request.url.path
    if len(path) < 2 or not path.endswith("/"):
        return ""
    probe = {**request.scope, "path": path.rstrip("/") or "/"}
    if any(route.matches(probe)[0] is not Match.NONE for route in request.app.routes):
        return f" (the routes take no trailing slash: {shortened(probe['path'])})"
    return ""


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    """Last resort: the traceback goes to the server log, the client gets a generic message."""
    request_id = getattr(request.state, "request_id", None)
    log.error("unhandled error", exc_info=exc, extra={"request_id": request_id, "route": request.url.path})
    return error_response(500, "internal server error", request_id=request_id)


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(APIError, _api_error)
    app.add_exception_handler(InputError, _input_error)
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(StarletteHTTPException, _http_exception)
    app.add_exception_handler(Exception, _unexpected)


def _doc(description: str, headers: dict[str, dict] | None = None) -> dict:
    doc: dict[str, Any] = {"model": ErrorResponse, "description": description}
    if headers:
        doc["headers"] = headers
    return doc


def _header(description: str) -> dict:
    return {"description": description, "schema": {"type": "string"}}


ERROR_DOCS: dict[int, dict] = {
    400: _doc("Malformed body: JSON syntax, multipart framing, an unreadable point-cloud file, or (OIP) a bad "
              "Inference-Header-Content-Length."),
    401: _doc("Missing or wrong API key (only when MFGNET_API_KEY is set).",
              {"WWW-Authenticate": _header("Bearer")}),
    404: _doc("Unknown model (or, on the versioned /v2 routes, version)."),
    408: _doc("The request body stalled (no data for MFGNET_BODY_TIMEOUT_S) or arrived slower than "
              "MFGNET_BODY_MIN_RATE; the connection is closed.", {"Connection": _header("close")}),
    413: _doc("Body larger than MFGNET_MAX_BODY_BYTES (MFGNET_MAX_UPLOAD_BYTES for multipart uploads), a cloud with "
              "more than MFGNET_MAX_POINTS points (MFGNET_MAX_FILE_POINTS for a file), a batch with too many pairs or "
              "points, or a JSON body with more values or strings than its clouds need."),
    415: _doc("A Content-Type (or Content-Encoding, or a file part's Content-Transfer-Encoding) this route does not "
              "read; the message names what it takes. Also a point-cloud format whose reader is not installed."),
    422: _doc("Validation failed: the message names the field and the problem (shape, dtype, NaN, range)."),
    503: _doc("Overloaded (more than MFGNET_MAX_QUEUE requests waiting), the model still loading (both with "
              "Retry-After), or the model failed to load.",
              {"Retry-After": _header("Seconds to wait before retrying (while overloaded or loading).")}),
    504: _doc("The registration did not finish within MFGNET_TIMEOUT_S."),
}


def error_docs(*statuses: int) -> dict[int | str, dict]:
    return {status: ERROR_DOCS[status] for status in statuses}
