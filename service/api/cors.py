"""CORS, on when ``MFGNET_CORS_ORIGINS`` is set: Starlette's middleware with the headers browser clients need,
``Inference-Header-Content-Length`` (the OIP binary tensor data extension) included both ways, and a refused
preflight answered as every error is: JSON ``{"error": ...}``."""

from __future__ import annotations

from fastapi import FastAPI
from starlette.datastructures import Headers
from starlette.middleware import cors
from starlette.responses import Response
from starlette.types import ASGIApp

from service.api.errors import error_response
from service.api.oip_request import HEADER_LENGTH

ALLOW_METHODS = ["GET", "POST"]
ALLOW_HEADERS = ["Authorization", "Content-Type", "X-Request-ID", HEADER_LENGTH]  # that requests may send
# that responses show to the page's script (Content-Disposition: the aligned download's file name)
EXPOSE_HEADERS = ["X-Request-ID", "Retry-After", "Content-Disposition", HEADER_LENGTH]


class CORSMiddleware(cors.CORSMiddleware):
    """Starlette's, with a refused preflight (400, ``Disallowed CORS origin, headers``, ...) as a JSON error."""

    def preflight_response(self, request_headers: Headers) -> Response:
        response = super().preflight_response(request_headers)
        if response.status_code < 400:
            return response
        headers = {k: v for k, v in response.headers.items() if k not in ("content-length", "content-type")}
        return error_response(response.status_code, bytes(response.body).decode(), headers)


def install(app: FastAPI, origins: list[str]) -> None:
    app.add_middleware(CORSMiddleware, **_options(origins))


def with_cors(app: ASGIApp, origins: list[str]) -> ASGIApp:
    """``app`` behind the middleware :func:`install` adds: for answers given outside it (the request context's own
    413s, 400s, 500s and 503s), which a cross-origin page could not read without its headers."""
    return CORSMiddleware(app, **_options(origins))


def _options(origins: list[str]) -> dict:
    return {"allow_origins": origins, "allow_methods": ALLOW_METHODS, "allow_headers": ALLOW_HEADERS,
            "expose_headers": EXPOSE_HEADERS}
