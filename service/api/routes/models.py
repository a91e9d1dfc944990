"""``GET /v1/models``: every discovered model with its load status (open, like the health routes)."""

from __future__ import annotations

from fastapi import APIRouter, Request

from service.api.deps import get_registry
from service.api.schemas import ModelList

router = APIRouter(prefix="/v1", tags=["models"])


@router.get("/models", response_model=ModelList, summary="Models, their manifests and load status")
async def list_models(request: Request) -> dict:
    registry, default = get_registry(request), request.app.state.runner.default_model
    models = []
    for entry in registry.entries.values():
        info = {"name": entry.name, "status": entry.status, "error": entry.error,
                "default": entry.name == default, "load_seconds": entry.load_seconds}
        if entry.registrar is not None:
            manifest = entry.registrar.manifest
            info.update(version=manifest.version, sha256=manifest.sha256, config=manifest.config,
                        accuracy=manifest.accuracy)
        models.append(info)
    return {"default_model": default, "models": models}
