"""Open Inference Protocol v2 (KServe / Triton): health, metadata and ``infer``.

Readiness is 503 with a JSON reason until every model is verified, loaded and warmed up.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from service.api import bodies
from service.api.deps import get_registry, get_runner, get_settings, require_api_key
from service.api.errors import APIError, error_docs
from service.api.registry import RETRY_AFTER_LOADING_S
from service.api.runner import infer_outputs, infer_parameters
from service.api.schemas import (
    ErrorResponse,
    InferResponse,
    LiveResponse,
    ModelMetadata,
    ModelReady,
    ReadyResponse,
    ServerMetadata,
)
from service.refine_modes import REFINE_MODES

router = APIRouter(prefix="/v2", tags=["inference protocol v2"])

SERVER_NAME = "mfgnet"
PLATFORM = "mfgnet_onnxruntime"
INPUTS = [
    {"name": "SOURCE", "datatype": "FP32", "shape": [-1, 3]},
    {"name": "TARGET", "datatype": "FP32", "shape": [-1, 3]},
]
OUTPUTS = [
    {"name": "TRANSFORM", "datatype": "FP32", "shape": [4, 4]},
    {"name": "SOURCE_INDEX", "datatype": "INT64", "shape": [-1]},
    {"name": "TARGET_INDEX", "datatype": "INT64", "shape": [-1]},
    {"name": "CREDIBILITY", "datatype": "FP32", "shape": [-1]},
]
_NOT_READY = {503: {"model": ErrorResponse, "description": "Not ready; the body says why (Retry-After set)."}}


def server_version() -> str:
    try:
        return version("mfgnet")
    except PackageNotFoundError:
        return "0+unknown"


@router.get("", response_model=ServerMetadata, summary="Server metadata")
async def server_metadata() -> dict:
    return {"name": SERVER_NAME, "version": server_version(), "extensions": []}


@router.get("/health/live", response_model=LiveResponse, summary="Liveness (answers while models load)")
async def live() -> dict:
    return {"live": True}


@router.get(
    "/health/ready", response_model=ReadyResponse, response_model_exclude_none=True, responses=_NOT_READY,
    summary="Readiness",
)
async def ready(request: Request):
    registry = get_registry(request)
    is_ready, reason = registry.readiness()
    errors = registry.errors()  # failed model -> reason (missing file, sha256 mismatch, ...)
    if not is_ready:
        body = {"error": f"not ready: {reason}", "ready": False, "models": registry.statuses()}
        return JSONResponse(
            {**body, "errors": errors} if errors else body,
            status_code=503,
            headers={"Retry-After": str(RETRY_AFTER_LOADING_S)},
        )
    return {"ready": True, "models": registry.statuses(), **({"errors": errors} if errors else {})}


@router.get("/models/{name}", response_model=ModelMetadata, responses=error_docs(404, 503), summary="Model metadata")
async def model_metadata(name: str, request: Request) -> dict:
    entry = get_registry(request).get(name)
    return {
        "name": entry.name,
        "versions": [entry.registrar.manifest.version],
        "platform": PLATFORM,
        "inputs": INPUTS,
        "outputs": OUTPUTS,
    }


@router.get("/models/{name}/ready", response_model=ModelReady, responses=error_docs(404, 503), summary="Model ready")
async def model_ready(name: str, request: Request) -> dict:
    entry = get_registry(request).get(name)  # 404 unknown, 503 loading or failed
    return {"name": entry.name, "ready": True}


@router.post(
    "/models/{name}/infer",
    response_model=InferResponse,
    summary="Register SOURCE onto TARGET (OIP v2)",
    description="Inputs SOURCE and TARGET: FP32, shape [N, 3] or [1, N, 3], flat or nested data. Request "
    f"parameters: iterations, keypoints, refine ({', '.join(REFINE_MODES)}), refine_points, drop_isolated, "
    "rotation_search (true, false or 'auto'). "
    "Outputs: TRANSFORM [4, 4] FP32 (src_to_tgt), "
    "SOURCE_INDEX / TARGET_INDEX [K] INT64, CREDIBILITY [K] FP32.",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/InferRequest"}}},
        }
    },
    responses=error_docs(400, 401, 404, 413, 415, 422, 503, 504),
    dependencies=[Depends(require_api_key)],
)
async def infer(name: str, request: Request) -> JSONResponse:
    settings, runner = get_settings(request), get_runner(request)
    if name not in get_registry(request).entries:  # fail fast, before reading the body
        raise APIError(404, f"unknown model {name!r}; see GET /v1/models")
    bodies.require_media_type(request, bodies.JSON)
    with runner.admit() as slot:
        body = await request.body()

        def work():
            call = bodies.infer_call_from_json(body, settings.max_points)
            entry, result = runner.register_one(call.pair, model=name)
            return call, entry, result

        (call, entry, result), queue_ms = await runner.run(slot, work)
    runner.observe(entry, result, queue_ms)
    response = {
        "model_name": entry.name,
        "model_version": entry.registrar.manifest.version,
        "id": call.request_id,
        "parameters": infer_parameters(result),
        "outputs": infer_outputs(result, call.outputs),
    }
    return JSONResponse(response)
