"""``POST /v1/register`` (JSON or multipart point-cloud file uploads) and ``POST /v1/register/batch``."""

from __future__ import annotations

from contextlib import ExitStack

from fastapi import APIRouter, Depends, Request

from service.api import bodies
from service.api.deps import get_runner, get_settings, require_api_key
from service.api.errors import error_docs
from service.api.responses import RenderedJSON
from service.api.runner import register_response
from service.api.schemas import (
    DROP_ISOLATED_DESCRIPTION,
    REFINE_DESCRIPTION,
    REFINE_POINTS_DESCRIPTION,
    ROTATION_SEARCH_DESCRIPTION,
    BatchResponse,
    RegisterResponse,
)
from service.refine_modes import REFINE_MODES, REFINE_POINTS_RANGE
from service.registrar import KEYPOINT_RANGE, MAX_ITERATIONS

router = APIRouter(prefix="/v1", tags=["register"], dependencies=[Depends(require_api_key)])

FILE_DESCRIPTION = (
    "A point-cloud file, its format found from its content: PLY (ascii, binary), PCD (ascii, binary, "
    "binary_compressed), LAS/LAZ, .npy/.npz (numbers [N, >=3] or fields x, y, z), XYZ/CSV/TXT. The first three "
    "columns or the x, y, z fields are used (colours, intensity, normals ignored); at most max_file_points points."
)
_MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["source", "target"],
    "properties": {
        "source": {"type": "string", "format": "binary", "description": FILE_DESCRIPTION},
        "target": {"type": "string", "format": "binary", "description": ".npy float32/float64 [M, 3]"},
        "model": {"type": "string"},
        "iterations": {"type": "integer", "minimum": 1, "maximum": MAX_ITERATIONS},
        "keypoints": {"type": "integer", "minimum": KEYPOINT_RANGE[0], "maximum": KEYPOINT_RANGE[1]},
        "refine": {"type": "string", "enum": list(REFINE_MODES), "description": REFINE_DESCRIPTION},
        "refine_points": {
            "type": "integer", "minimum": REFINE_POINTS_RANGE[0], "maximum": REFINE_POINTS_RANGE[1],
            "description": REFINE_POINTS_DESCRIPTION,
        },
        "drop_isolated": {"type": "boolean", "default": True, "description": DROP_ISOLATED_DESCRIPTION},
        "initial_transform": {"type": "string", "description": "JSON 4x4 array"},
        "return_correspondences": {"type": "boolean", "default": True},
        "return_iterations": {"type": "boolean", "default": False},
        "rotation_search": {
            "anyOf": [{"type": "boolean"}, {"type": "string", "enum": ["auto"]}],
            "description": ROTATION_SEARCH_DESCRIPTION,
        },
    },
}


def _request_body(schema_name: str, multipart: bool) -> dict:
    content = {"application/json": {"schema": {"$ref": f"#/components/schemas/{schema_name}"}}}
    if multipart:
        content["multipart/form-data"] = {"schema": _MULTIPART_SCHEMA}
    return {"requestBody": {"required": True, "content": content}}


@router.post(
    "/register",
    response_model=RegisterResponse,
    response_model_exclude_none=True,
    summary="Register source onto target",
    description="The rigid pose src_to_tgt. Send JSON (RegisterRequest) or multipart/form-data with two "
    "point-cloud files `source` and `target` (PLY, PCD, LAS/LAZ, NPY/NPZ, XYZ/CSV/TXT) and the options as form "
    "fields.",
    openapi_extra=_request_body("RegisterRequest", multipart=True),
    responses=error_docs(400, 401, 404, 408, 413, 415, 422, 503, 504),
)
async def register(request: Request) -> RenderedJSON:
    settings, runner = get_settings(request), get_runner(request)
    kind = bodies.require_media_type(request, bodies.JSON, bodies.MULTIPART)
    with runner.admit() as slot, ExitStack() as held_until_done:
        if kind == bodies.JSON:
            held = held_until_done.enter_context(
                await bodies.read_body(request, runner.body_budget, settings.max_body_bytes))

            def decode() -> bodies.Pair:  # takes the body: it is freed once parsed, before the pipeline runs
                with held:
                    return bodies.register_pair_from_json(held.take(), settings.max_points)
        else:
            form = await bodies.read_register_form(request)

            def decode() -> bodies.Pair:
                return bodies.register_pair_from_form(form, settings.max_file_points)

        def work():
            pair = decode()
            entry, result = runner.register_one(pair)
            return entry, pair, result

        (entry, pair, result), queue_ms = await runner.run(slot, work, request)
    runner.observe(entry, result, queue_ms)
    return RenderedJSON(register_response(entry, pair, result, queue_ms))  # response_model: for the docs only


@router.post(
    "/register/batch",
    response_model=BatchResponse,
    response_model_exclude_none=True,
    summary="Register several pairs",
    description="Each pair is checked before any runs; the results equal single /v1/register calls.",
    openapi_extra=_request_body("BatchRequest", multipart=False),
    responses=error_docs(400, 401, 404, 408, 413, 415, 422, 503, 504),
)
async def register_batch(request: Request) -> RenderedJSON:
    settings, runner = get_settings(request), get_runner(request)
    bodies.require_media_type(request, bodies.JSON)
    with runner.admit() as slot, await bodies.read_body(request, runner.body_budget, settings.max_body_bytes) as held:

        def work():
            with held:
                pairs = bodies.batch_pairs_from_json(held.take(), settings.max_points, settings.max_batch)
            return pairs, runner.register_batch(pairs)

        (pairs, done), queue_ms = await runner.run(slot, work, request)
    for entry, result in done:
        runner.observe(entry, result, queue_ms)
    results = [register_response(e, p, r, queue_ms) for p, (e, r) in zip(pairs, done, strict=True)]
    return RenderedJSON({"results": results})
