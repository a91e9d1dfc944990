"""FastAPI dependencies: the app's shared objects and the optional API key."""

from __future__ import annotations

import hmac

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.errors import APIError
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
