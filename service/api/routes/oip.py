"""Open Inference Protocol v2 (KServe / Triton): health, metadata and ``infer``, with the binary tensor data
extension (``binary_tensor_data``) as ``tritonclient.http`` uses it by default. The model routes are served under
``/v2/models/{name}/versions/{version}`` too, for the one version each model has (its manifest's).

Readiness is 503 with a JSON reason until every model is verified, loaded and warmed up (not the 4xx of the OIP
text: every consumer reads 503 as not ready, Kubernetes probes and ``tritonclient`` included; docs/DEPLOYMENT.md).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response

from service.api import oip_request
from service.api.bodies import read_body
from service.api.deps import get_registry, get_runner, get_settings, refuse_query_on_post, require_api_key
from service.api.errors import APIError, error_docs
from service.api.oip_request import HEADER_LENGTH, OCTET_STREAM
from service.api.oip_response import infer_response
from service.api.registry import RETRY_AFTER_LOADING_S, ModelEntry, unknown_model
from service.api.schemas import (
    InferResponse,
    LiveResponse,
    ModelMetadata,
    ModelReady,
    NotReadyResponse,
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
    {"name": "INITIAL_TRANSFORM", "datatype": "FP32", "shape": [4, 4]},  # optional
]
OUTPUTS = [
    {"name": "TRANSFORM", "datatype": "FP32", "shape": [4, 4]},
    {"name": "SOURCE_INDEX", "datatype": "INT64", "shape": [-1]},
    {"name": "TARGET_INDEX", "datatype": "INT64", "shape": [-1]},
    {"name": "CREDIBILITY", "datatype": "FP32", "shape": [-1]},
]
EXTENSIONS = ("binary_tensor_data",)
_NOT_READY = {503: {"model": NotReadyResponse, "description": "Not ready; the body says why and each model's status.",
                    "headers": {"Retry-After": {"description": "Seconds to wait before asking again.",
                                                "schema": {"type": "string"}}}}}


def server_version() -> str:
    try:
        return version("mfgnet")
    except PackageNotFoundError:
        return "0+unknown"


@router.get("", response_model=ServerMetadata, summary="Server metadata")
async def server_metadata() -> dict:
    return {"name": SERVER_NAME, "version": server_version(), "extensions": list(EXTENSIONS)}


@router.get("/health/live", response_model=LiveResponse, summary="Liveness (answers while models load)")
async def live() -> dict:
    return {"live": True}


@router.get(
    "/health/ready", response_model=ReadyResponse, response_model_exclude_none=True, responses=_NOT_READY,
    summary="Readiness",
)
async def ready(request: Request) -> dict | JSONResponse:
    registry = get_registry(request)
    is_ready, reason = registry.readiness()
    errors = registry.errors()  # failed model -> reason (missing file, sha256 mismatch, ...)
    if not is_ready:
        statuses = registry.statuses()
        body = {"error": f"not ready: {reason}", "ready": False, "models": statuses}
        loading = any(status == "loading" for status in statuses.values())  # else it will not become ready by waiting
        return JSONResponse(
            {**body, "errors": errors} if errors else body,
            status_code=503,
            headers={"Retry-After": str(RETRY_AFTER_LOADING_S)} if loading else None,
        )
    return {"ready": True, "models": registry.statuses(), **({"errors": errors} if errors else {})}


def versioned_entry(request: Request, name: str, version: str) -> ModelEntry:
    """The model ``name`` if ``version`` is its version (each model serves one: its manifest's); 404 naming the
    versions otherwise, 404 / 503 as :meth:`ModelRegistry.get` for the name."""
    entry = get_registry(request).get(name)
    versions = [entry.registrar.manifest.version]  # get() checked it is loaded
    if version not in versions:
        raise APIError(404, f"model {name!r} has no version {version[:80]!r}; its versions: {versions}")
    return entry


def _metadata(entry: ModelEntry) -> dict:
    return {
        "name": entry.name,
        "versions": [entry.registrar.manifest.version],
        "platform": PLATFORM,
        "inputs": INPUTS,
        "outputs": OUTPUTS,
    }


@router.get("/models/{name}", response_model=ModelMetadata, responses=error_docs(404, 503), summary="Model metadata")
async def model_metadata(name: str, request: Request) -> dict:
    return _metadata(get_registry(request).get(name))


@router.get(
    "/models/{name}/versions/{version}", response_model=ModelMetadata, responses=error_docs(404, 503),
    summary="Model metadata, of the model's version (404 for another)",
)
async def model_version_metadata(name: str, version: str, request: Request) -> dict:
    return _metadata(versioned_entry(request, name, version))


@router.get("/models/{name}/ready", response_model=ModelReady, responses=error_docs(404, 503), summary="Model ready")
async def model_ready(name: str, request: Request) -> dict:
    entry = get_registry(request).get(name)  # 404 unknown, 503 loading or failed
    return {"name": entry.name, "ready": True}


@router.get(
    "/models/{name}/versions/{version}/ready", response_model=ModelReady, responses=error_docs(404, 503),
    summary="Model ready, of the model's version (404 for another)",
)
async def model_version_ready(name: str, version: str, request: Request) -> dict:
    entry = versioned_entry(request, name, version)  # 404 unknown name or version, 503 loading or failed
    return {"name": entry.name, "ready": True}


INFER_DESCRIPTION = f"""Register SOURCE onto TARGET.

**Inputs** SOURCE and TARGET: FP32, shape [N, 3] or [1, N, 3] (x, y, z rows, any units: the outputs are in the
same units), each either as JSON `data` (flat and row-major, or nested as the shape) or as binary tensor data. Optional
INITIAL_TRANSFORM: FP32, shape [4, 4] or [1, 4, 4], a rigid src_to_tgt guess (row-major, the clouds' units), as
`initial_transform` of `/v1/register`: the network starts from it, and it is kept where it fits better than the
network's poses (with refine 'none' too, unrefined).

**Request parameters** (all optional): iterations, keypoints, refine ({', '.join(REFINE_MODES)}), refine_points,
drop_isolated, rotation_search (true, false or 'auto'), binary_data_output (true: every output as binary data
unless the output's own `binary_data` says otherwise). Others are ignored, but for `initial_transform`: a 422
naming the INITIAL_TRANSFORM input, which takes the guess. Triton's shared memory
(`shared_memory_region`, ... on an input or output) and classification (`classification` on an output) extensions
are not served: a 422 naming the parameter.

**Outputs** (all four when `outputs` is absent, else those named, in that order):
- TRANSFORM, FP32 [4, 4]: the homogeneous rigid transform src_to_tgt, row-major, in the caller's units
  (`target ~= source @ R.T + t` with `R = TRANSFORM[:3, :3]`, `t = TRANSFORM[:3, 3]`; last row 0 0 0 1).
- SOURCE_INDEX, INT64 [K]: per keypoint match, the row of the SOURCE input.
- TARGET_INDEX, INT64 [K]: the row of the TARGET input it was matched to.
- CREDIBILITY, FP32 [K]: the predicted probability (0..1) that the match is correct.

K is the number of keypoint matches (the model's keypoints, or the `keypoints` parameter; after a refined rotation
search on a model that searches a subsample, that subsample's, 32 for `general`).
**Response parameters**: iterations, inlier_ratio (0..1), residual_rms (caller's units), reliable, warnings
(one per line, '\\n'-joined), total_ms (pipeline time, ms), stability (when defined), search_ms (when the rotation
search ran).

**Binary tensor data** (`binary_tensor_data` in `GET /v2`): a request may put any input's values after the
JSON object, as little-endian float32 bytes (row-major, no padding): the input gets
`parameters.binary_data_size` (bytes, = N x 3 x 4; 64 for INITIAL_TRANSFORM) instead of `data`, and the
`{HEADER_LENGTH}` header gives the JSON object's length in bytes. The binary parts follow in the order of `inputs`
and must fill the rest of the body exactly. Outputs asked for with `parameters.binary_data: true` (or all, with the
request parameter `binary_data_output: true`) come back the same way: `parameters.binary_data_size` instead of
`data`, their bytes after the JSON object in output order (INT64 as little-endian int64), the response's
`{HEADER_LENGTH}` header giving the JSON length and its Content-Type {OCTET_STREAM}.

The body may be sent without a Content-Type, or as application/json or {OCTET_STREAM}; not compressed.
"""


INFER_ROUTE = {
    "response_model": InferResponse,
    "description": INFER_DESCRIPTION,
    "openapi_extra": {
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {"schema": {"$ref": "#/components/schemas/InferRequest"}},
                OCTET_STREAM: {
                    "schema": {
                        "type": "string",
                        "format": "binary",
                        # a Media Type Object has no "description" in OpenAPI 3.1: the schema carries it
                        "description": f"Binary tensor data: the InferRequest JSON ({HEADER_LENGTH} bytes), then "
                        "the binary inputs' bytes.",
                    },
                },
            },
        },
        "parameters": [
            {
                "name": HEADER_LENGTH,
                "in": "header",
                "required": False,
                "schema": {"type": "integer", "minimum": 1},  # the JSON inference request comes first: never empty
                "description": "Binary tensor data extension: the length in bytes of the JSON InferRequest that "
                "starts the body; the binary inputs follow it. Absent for a JSON-only body.",
            }
        ],
    },
    "responses": {
        200: {
            "description": f"The InferResponse as application/json, or, when an output is sent as binary data, as "
            f"{OCTET_STREAM}: the InferResponse JSON ({HEADER_LENGTH} bytes), then the binary outputs' bytes.",
            "content": {OCTET_STREAM: {"schema": {"type": "string", "format": "binary"}}},
            "headers": {
                HEADER_LENGTH: {
                    "schema": {"type": "integer", "minimum": 0},
                    "description": f"With {OCTET_STREAM}: the length in bytes of the InferResponse JSON that starts "
                    "the body.",
                },
            },
        },
        **error_docs(400, 401, 404, 408, 413, 415, 422, 503, 504),
    },
    "dependencies": [Depends(require_api_key), Depends(refuse_query_on_post)],
}


@router.post("/models/{name}/infer", summary="Register SOURCE onto TARGET (OIP v2)", **INFER_ROUTE)
async def infer(name: str, request: Request) -> Response:
    if name not in get_registry(request).entries:  # fail fast, before reading the body
        raise unknown_model(name)
    return await _infer(name, request)


@router.post(
    "/models/{name}/versions/{version}/infer",
    summary="Register SOURCE onto TARGET (OIP v2), with the model's version (404 for another)", **INFER_ROUTE,
)
async def infer_version(name: str, version: str, request: Request) -> Response:
    versioned_entry(request, name, version)  # before reading the body
    return await _infer(name, request)


async def _infer(name: str, request: Request) -> Response:
    settings, runner = get_settings(request), get_runner(request)
    kind = oip_request.check_media_type(request)
    length = oip_request.header_length(request)
    octet_stream = kind == OCTET_STREAM
    with runner.admit() as slot, await read_body(request, runner.body_budget, settings.max_body_bytes,
                                     settings.timeout_s) as held:
        # a 413 the header or the value count tells (and the checks before it) before the wait for a worker
        await run_in_threadpool(oip_request.check_infer_head, held.peek(), settings.max_points, length, octet_stream)

        def decode() -> oip_request.InferCall:
            with held:  # the body is freed once decoded, before the pipeline runs
                return oip_request.infer_call(held.take(), length, settings.max_points, octet_stream,
                                              values_checked=True)

        def work(call: oip_request.InferCall):
            entry, result = runner.register_one(call.pair, model=name)
            return call, entry, result

        (call, entry, result), queue_ms = await runner.run(slot, work, request, decode)
    runner.observe(entry, result, queue_ms)
    head = {"model_name": entry.name, "model_version": entry.registrar.manifest.version}
    if call.request_id is not None:  # OIP: id only when the request had one
        head["id"] = call.request_id
    return infer_response(head, result, call.outputs, call.binary_outputs)
