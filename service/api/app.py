"""``create_app(settings)`` builds the FastAPI app; ``run_server(settings)`` serves it with uvicorn (one process).

Start-up is instant: models load in a background thread, ``/v2/health/live`` answers at once and
``/v2/health/ready`` turns 200 once every model is verified, loaded and warmed up.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from service.api import cors
from service.api.body_budget import BodyBudget
from service.api.errors import install_error_handlers
from service.api.head import HeadAsGetMiddleware
from service.api.limiter import InferenceLimiter
from service.api.metrics import Metrics
from service.api.middleware import RequestContextMiddleware
from service.api.ranges import IgnoreUnservableRanges
from service.api.registry import ModelEntry, ModelRegistry, UnknownModelsError
from service.api.routes import docs, models, oip, page, register
from service.api.routes import metrics as metrics_routes
from service.api.runner import Runner
from service.api.schemas import BatchRequest, InferRequest, RegisterRequest
from service.api.security_headers import SecurityHeadersMiddleware
from service.api.server_options import ServerOptionsMiddleware
from service.blas_threads import use_one_blas_thread
from service.core.config import Settings
from service.core.logging import configure_logging

# Request bodies are read by the routes themselves (content-type dispatch, point counting before
# conversion), so their schemas are added to the OpenAPI components here.
REQUEST_SCHEMAS = (RegisterRequest, BatchRequest, InferRequest)


def effective_default_model(settings: Settings, registry: ModelRegistry) -> str:
    """``MFGNET_DEFAULT_MODEL``, or the only served model when that one is not served and the variable is not set (a
    server started on a single ``--model-dir`` model with the bundled models off). :class:`UnknownModelsError` where a
    default set by name, or ``general`` among several models, is not served: every request that names no model, the
    page's among them, would be a 404."""
    served = registry.entries
    if settings.default_model in served or not served:
        return settings.default_model
    if len(served) == 1 and "default_model" not in settings.model_fields_set:  # set by name: not replaced
        return next(iter(served))
    raise UnknownModelsError(
        f"MFGNET_DEFAULT_MODEL is {settings.default_model!r}, which this server does not serve (it serves "
        f"{', '.join(sorted(served))}): set MFGNET_DEFAULT_MODEL to one of them, or serve it (MFGNET_MODELS, "
        "MFGNET_MODEL_DIRS)")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    use_one_blas_thread()  # here, on the main thread: the models load in a background thread
    metrics = Metrics()
    registry = ModelRegistry.discover(
        settings.model_dirs,
        bundled=settings.bundled_models,
        only=settings.models,
        threads=settings.threads,
        strict=settings.strict_readiness,
        on_loaded=lambda entry: _record_load(metrics, entry),
    )
    limiter = InferenceLimiter(settings.max_concurrency, settings.max_queue, settings.timeout_s)
    for entry in registry.entries.values():
        metrics.model_ready.labels(model=entry.name).set_function(lambda e=entry: float(e.status == "ready"))
    metrics.slots.set_function(lambda: limiter.taken)
    budget = BodyBudget(settings.max_buffered_bytes)
    metrics.body_bytes.set_function(lambda: budget.held)
    metrics.running.set_function(lambda: limiter.running)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        registry.start()  # background thread: liveness answers while models load
        try:
            yield
        finally:
            limiter.shutdown()

    app = FastAPI(
        title="MFGNet registration service",
        version=oip.server_version(),
        description="Rigid registration of partial point clouds (MFGNet, ONNX Runtime). Poses are src_to_tgt.",
        lifespan=lifespan,
        docs_url=None,  # /docs and /redoc come from routes/docs.py, with their assets served locally
        redoc_url=None,
        redirect_slashes=False,  # a 307 to the path without its slash made clients send a POST's body twice (errors.py)
    )
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.registry = registry
    app.state.limiter = limiter
    app.state.runner = Runner(
        registry, limiter, metrics, budget, effective_default_model(settings, registry), settings.default_refine,
        settings.default_rotation_search,
    )

    install_error_handlers(app)
    for router in (register.router, page.router, models.router, oip.router, metrics_routes.router):
        app.include_router(router)
    page.install(app)
    docs.install(app)
    if settings.cors_origins:
        cors.install(app, settings.cors_origins)  # with the OIP binary extension's header; refusals as JSON
    app.add_middleware(IgnoreUnservableRanges)  # the static files' Range: a unit or form they cannot serve is ignored
    app.add_middleware(HeadAsGetMiddleware)  # inside the request context: the access log and metrics say HEAD
    app.add_middleware(ServerOptionsMiddleware)  # OPTIONS *: inside the request context (logged, counted)
    app.add_middleware(RequestContextMiddleware, metrics=metrics, max_body_bytes=settings.max_body_bytes,
                       max_upload_bytes=settings.max_upload_bytes, body_timeout_s=settings.body_timeout_s,
                       body_min_rate=settings.body_min_rate, cors_origins=settings.cors_origins)
    app.add_middleware(SecurityHeadersMiddleware)  # outermost: on the request context's own 413s and 500s too
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def _record_load(metrics: Metrics, entry: ModelEntry) -> None:
    metrics.model_load.labels(model=entry.name).set(entry.load_seconds or 0.0)


REQUEST_ID_PARAMETER = {
    "name": "X-Request-ID",
    "in": "header",
    "required": False,
    "schema": {"type": "string"},
    "description": "The request's id for the logs and the answer's X-Request-ID: kept where it is 1-128 letters, "
    "digits and ._:- (another value is replaced by a new id, not refused).",
}
REQUEST_ID_HEADER = {
    "schema": {"type": "string"},
    "description": "The request's X-Request-ID where it sent a usable one, else a new id; the access log line's "
    "request_id.",
}


def _openapi(app: FastAPI) -> dict:
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in REQUEST_SCHEMAS:
            body = model.model_json_schema(ref_template="#/components/schemas/{model}", mode="validation")
            components.update(body.pop("$defs", {}))
            components[model.__name__] = body
        # Every error body, validation included, is an ErrorResponse (not FastAPI's HTTPValidationError).
        for path in schema.get("paths", {}).values():
            for operation in path.values():
                doc = operation.get("responses", {}).get("422")
                if doc and "HTTPValidationError" in str(doc) and _never_invalid(operation):
                    del operation["responses"]["422"]
                elif doc and "HTTPValidationError" in str(doc):
                    operation["responses"]["422"] = {
                        "description": "Validation failed",
                        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}},
                    }
        for name in ("HTTPValidationError", "ValidationError"):
            components.pop(name, None)
        key_optional = not app.state.settings.api_key
        for path in schema.get("paths", {}).values():
            for operation in path.values():
                # every answer carries a request id (RequestContextMiddleware)
                operation.setdefault("parameters", []).append(REQUEST_ID_PARAMETER)
                for response in operation.get("responses", {}).values():
                    response.setdefault("headers", {})["X-Request-ID"] = REQUEST_ID_HEADER
                # without MFGNET_API_KEY the key is not asked for: an empty requirement beside it says so to clients
                # and generators (which otherwise demand a token); with it, the bearer token alone
                if key_optional and operation.get("security") == [{"HTTPBearer": []}]:
                    operation["security"] = [{"HTTPBearer": []}, {}]
        app.openapi_schema = schema
    return app.openapi_schema


def _never_invalid(operation: dict) -> bool:
    """Whether FastAPI's automatic 422 can never happen: no body and only string path parameters (the /v2 model
    routes), which any path segment satisfies."""
    return "requestBody" not in operation and all(
        p.get("in") == "path" and p.get("schema", {}).get("type") == "string" for p in operation.get("parameters", [])
    )


def run_server(settings: Settings | None = None) -> None:
    """Serve on ``settings.host:settings.port`` in this process until interrupted."""
    import uvicorn

    from service.api.http_protocol import connection_limits, h11_protocol

    settings = settings or Settings()
    configure_logging(settings.log_level)
    app = create_app(settings)
    max_connections, backlog = connection_limits(settings.max_connections)  # within the open-file limit
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        workers=1,
        # uvicorn's h11, with a deadline on the request headers and a cap on open connections; its 408s and refused
        # connections counted in the app's metrics
        http=h11_protocol(settings.header_timeout_s, app.state.metrics, max_connections),
        backlog=backlog,
        access_log=False,  # one JSON line per request comes from RequestContextMiddleware
        log_config=None,  # keep the JSON handlers configure_logging installed
        server_header=False,
        timeout_graceful_shutdown=5,
        timeout_keep_alive=settings.keep_alive_s,
    )
