"""``POST /v1/register`` (JSON or multipart point-cloud file uploads) and ``POST /v1/register/batch``."""

from __future__ import annotations

from contextlib import ExitStack

from fastapi import APIRouter, Depends, Request

from service.api import bodies
from service.api.deps import get_runner, get_settings, refuse_query_on_post, require_api_key
from service.api.errors import error_docs
from service.api.responses import RenderedJSON
from service.api.runner import register_response
from service.api.schemas import (
    BatchResponse,
    RegisterOptions,
    RegisterResponse,
)

router = APIRouter(prefix="/v1", tags=["register"],
                   dependencies=[Depends(require_api_key), Depends(refuse_query_on_post)])

FILE_DESCRIPTION = (
    "A point-cloud file, its format found from its content: PLY (ascii, binary), PCD (ascii, binary, "
    "binary_compressed), LAS/LAZ, E57, .npy/.npz (numbers [N, >=3] or fields x, y, z), XYZ/CSV/TXT, Leica PTS/PTX. "
    "The first three columns or the x, y, z fields are used (colours, intensity, normals ignored); at most the "
    "server's MFGNET_MAX_FILE_POINTS points."
)
INITIAL_TRANSFORM_FIELD = (
    "The JSON option initial_transform (a rigid 4x4 src_to_tgt guess, row-major, in the clouds' units) as JSON text, "
    "e.g. [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]."
)


def _form_field(prop: dict) -> dict:
    """One ``RegisterOptions`` property as a form field: the same type, range, enum and description, without the
    JSON ``null`` (a form field is given or left out)."""
    field = {k: v for k, v in prop.items() if k not in ("anyOf", "title") and not (k == "default" and v is None)}
    kinds = [kind for kind in prop.get("anyOf", []) if kind.get("type") != "null"]
    if len(kinds) == 1:
        field.update(kinds[0])
    elif kinds:
        field["anyOf"] = kinds
    return field


def multipart_schema() -> dict:
    """The ``multipart/form-data`` body of ``POST /v1/register``: two point-cloud files and the options of
    :class:`RegisterOptions` as text fields, built from its JSON schema so that both say the same (types, ranges,
    enums, descriptions); ``initial_transform`` is JSON text. Other fields are refused (422), as in the JSON body."""
    options = RegisterOptions.model_json_schema()["properties"]
    properties: dict[str, dict] = {
        "source": {"type": "string", "format": "binary", "description": f"The source cloud. {FILE_DESCRIPTION}"},
        "target": {"type": "string", "format": "binary", "description": f"The target cloud. {FILE_DESCRIPTION}"},
    }
    for name, prop in options.items():
        properties[name] = _form_field(prop)
    properties["initial_transform"] = {"type": "string", "contentMediaType": "application/json",
                                       "description": INITIAL_TRANSFORM_FIELD}
    return {"type": "object", "required": ["source", "target"], "properties": properties,
            "additionalProperties": False}


_MULTIPART_SCHEMA = multipart_schema()


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
    "point-cloud files `source` and `target` (PLY, PCD, LAS/LAZ, E57, NPY/NPZ, XYZ/CSV/TXT, PTS/PTX) and the options "
    "as form fields.",
    openapi_extra=_request_body("RegisterRequest", multipart=True),
    responses=error_docs(400, 401, 404, 408, 413, 415, 422, 503, 504),
)
async def register(request: Request) -> RenderedJSON:
    settings, runner = get_settings(request), get_runner(request)
    kind = bodies.require_media_type(request, bodies.JSON, bodies.MULTIPART)
    with runner.admit() as slot, ExitStack() as held_until_done:
        if kind == bodies.JSON:
            held = held_until_done.enter_context(
                await bodies.read_body(request, runner.body_budget, settings.max_body_bytes,
                                     settings.timeout_s))
            # 413 before the wait for a worker
            await bodies.refuse_too_many_values(held, bodies.check_register_values, settings.max_points)

            def decode() -> bodies.Pair:  # takes the body: it is freed once parsed, before the pipeline runs
                with held:
                    return bodies.register_pair_from_json(held.take(), settings.max_points, values_checked=True)
        else:
            form = await bodies.read_register_form(request)
            await bodies.refuse_oversized_uploads(form, settings.max_file_points)  # 413 before the wait for a worker

            def decode() -> bodies.Pair:
                return bodies.register_pair_from_form(form, settings.max_file_points)

        def work(pair: bodies.Pair):
            entry, result = runner.register_one(pair)
            return entry, pair, result

        (entry, pair, result), queue_ms = await runner.run(slot, work, request, decode)
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
    with runner.admit() as slot, await bodies.read_body(request, runner.body_budget, settings.max_body_bytes,
                                     settings.timeout_s) as held:
        # 413 before the wait for a worker
        await bodies.refuse_too_many_values(held, bodies.check_batch_values, settings.max_points)

        def decode() -> list[bodies.Pair]:
            with held:
                return bodies.batch_pairs_from_json(held.take(), settings.max_points, settings.max_batch,
                                                    values_checked=True)

        def work(pairs: list[bodies.Pair]):
            return pairs, runner.register_batch(pairs)

        (pairs, done), queue_ms = await runner.run(slot, work, request, decode)
    for entry, result in done:
        runner.observe(entry, result, queue_ms)
    results = [register_response(e, p, r, queue_ms) for p, (e, r) in zip(pairs, done, strict=True)]
    return RenderedJSON({"results": results})
