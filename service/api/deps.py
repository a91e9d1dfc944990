"""FastAPI dependencies: the app's shared objects and the optional API key."""

from __future__ import annotations

import hmac
from urllib.parse import parse_qsl

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.errors import APIError, shortened
from service.api.metrics import Metrics
from service.api.registry import ModelRegistry
from service.api.runner import Runner
from service.core.config import Settings

bearer = HTTPBearer(auto_error=False, description="Needed only when the server sets MFGNET_API_KEY.")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_registry(request: Request) -> ModelRegistry:
    return request.app.state.registry


def get_runner(request: Request) -> Runner:
    return request.app.state.runner


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def require_api_key(
    request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(bearer)
) -> None:
    """401 unless ``Authorization: Bearer <key>`` matches (constant-time compare); open when no key is set."""
    expected = get_settings(request).api_key
    if expected is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not given or not hmac.compare_digest(given.encode(), expected.get_secret_value().encode()):
        message = "missing or invalid API key; send 'Authorization: Bearer <key>'"
        raise APIError(401, message, headers={"WWW-Authenticate": "Bearer"})


def refuse_query_on_post(request: Request) -> None:
    """400 naming a POST request's query parameters: no route reads them, so an option sent there (``?model=clean``)
    would be ignored without a word."""
    query = request.scope.get("query_string", b"").decode("latin-1")  # as sent: a "#" in it is no fragment here
    if request.method != "POST" or not query:
        return
    names = sorted({name for name, _ in parse_qsl(query, keep_blank_values=True)}) or [query]
    raise APIError(400, shortened(f"query parameters are not read on POST routes ({', '.join(names[:5])}); send "
                                  "options in the request body (JSON fields, form fields or OIP parameters)"))
