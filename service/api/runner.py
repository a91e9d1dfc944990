"""Runs registrations for the routes: model lookup, option checks, the pipeline in a bounded worker,
and the shaping of results into response dicts. One :class:`Registrar` per model is shared by every
request; its ONNX sessions are thread-safe, so concurrent results equal sequential ones."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from functools import cache
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from service.api.bodies import Pair
from service.api.body_budget import BodyBudget
from service.api.errors import APIError
from service.api.limiter import InferenceLimiter, Slot
from service.api.metrics import Metrics
from service.api.registry import ModelEntry, ModelRegistry
from service.api.schemas import RegisterOptions
from service.checks import max_abs
from service.options import check_refine_points_refined
from service.pose_json import pose_fields
from service.refine_modes import SERVICE_DEFAULT_REFINE
from service.registrar import (
    DEFAULT_WORKING_SIZE,
    InputError,
    Registrar,
    RegistrationResult,
    check_cloud,
    check_transform,
)
from service.request_defaults import request_defaults
from service.search_mode import SERVICE_DEFAULT_ROTATION_SEARCH

if TYPE_CHECKING:
    from starlette.requests import Request

T = TypeVar("T")
FLOAT32_MAX = float(np.finfo(np.float32).max)


@cache
def supports_option(registrar_type: type, option: str) -> bool:
    """Whether ``registrar_type.register`` takes ``option`` (e.g. ``rotation_search``): a parameter of its own or a
    field of the options object it takes as keyword overrides (``option_names``)."""
    names = getattr(registrar_type, "option_names", frozenset())
    return option in names or option in inspect.signature(registrar_type.register).parameters


class Runner:
    def __init__(
        self,
        registry: ModelRegistry,
        limiter: InferenceLimiter,
        metrics: Metrics,
        body_budget: BodyBudget,
        default_model: str,
        default_refine: str = SERVICE_DEFAULT_REFINE,
        default_rotation_search: str = SERVICE_DEFAULT_ROTATION_SEARCH,
    ):
        self.registry = registry
        self.limiter = limiter
        self.body_budget = body_budget  # JSON and OIP bodies held at once
        self.metrics = metrics
        self.default_model = default_model
        self.default_refine = default_refine  # applied when a request names no refinement
        self.default_rotation_search = default_rotation_search  # "off" | "on" | "auto", for refined requests

    # -- scheduling --------------------------------------------------------------------------------
    def admit(self) -> Slot:
        return self.limiter.admit()

    async def run(self, slot: Slot, work: Callable[..., T], request: Request | None = None,
                  decode: Callable[[], Any] | None = None) -> tuple[T, float]:
        """``work()`` in a worker within the deadline -> ``(result, ms spent waiting for a worker)``; with the HTTP
        ``request``, cancelled when its client goes away; with ``decode``, ``work(decode())``, the deadline stopped
        while ``decode`` reads the body (:meth:`Slot.run`: a 413 for its size whatever the deadline)."""
        return await slot.run(work, request.is_disconnected if request is not None else None, decode)

    # -- the pipeline (worker threads) -------------------------------------------------------------
    def resolve(self, name: str | None) -> ModelEntry:
        return self.registry.get(name or self.default_model)

    def prepare(self, pair: Pair, model: str | None = None, prefix: str = "") -> tuple[ModelEntry, dict[str, Any]]:
        """Model entry and ``register`` keyword arguments; every check that can fail runs here (422/404/503)."""
        try:
            entry = self.resolve(model or pair.options.model)
        except APIError as exc:  # unknown, loading or failed: in a batch, which pair named it
            if prefix:
                exc.message = f"{prefix}model: {exc.message}"
            raise
        registrar = entry.registrar
        assert registrar is not None
        o = pair.options
        refine, search = request_defaults(o.refine, o.rotation_search, default_refine=self.default_refine,
                                          default_rotation_search=self.default_rotation_search)
        try:
            check_refine_points_refined(refine, o.refine_points, defaulted=o.refine is None)
        except InputError as exc:
            raise APIError(422, f"invalid request: {prefix}{exc}") from None
        kwargs: dict[str, Any] = {
            "iterations": o.iterations,
            "keypoints": o.keypoints,
            "refine": refine,
            "initial_transform": o.initial_transform,
            "return_iterations": o.return_iterations,
        }
        if not o.drop_isolated:
            if not supports_option(type(registrar), "drop_isolated"):
                raise APIError(422, f"invalid request: {prefix}drop_isolated: not supported by this server")
            kwargs["drop_isolated"] = False
        if o.refine_points is not None:
            if not supports_option(type(registrar), "refine_points"):
                raise APIError(422, f"invalid request: {prefix}refine_points: not supported by this server")
            kwargs["refine_points"] = o.refine_points
        if search and supports_option(type(registrar), "rotation_search"):
            kwargs["rotation_search"] = search  # True or "auto"
        elif search and o.rotation_search:  # asked for explicitly; a server default is simply not applied
            raise APIError(422, f"invalid request: {prefix}rotation_search: not supported by this server")
        source_name, target_name, transform_name = pair.names
        try:
            check_cloud(pair.source, source_name)
            check_cloud(pair.target, target_name)
            registrar.check_options(o.iterations, o.keypoints, DEFAULT_WORKING_SIZE, refine)  # schema: refine_points
        except InputError as exc:
            raise APIError(422, f"invalid request: {prefix}{exc}") from None
        if o.initial_transform is not None:
            try:
                _, translation = check_transform(o.initial_transform)
                reach = max_abs(translation) + max_abs(pair.source)
                if not reach <= FLOAT32_MAX:  # the moved source would overflow the pipeline's sums
                    raise InputError("initial_transform: moves the source beyond the float32 range")
            except InputError as exc:  # its messages begin with the option's name
                message = str(exc).removeprefix("initial_transform")
                raise APIError(422, f"invalid request: {prefix}{transform_name}{message}") from None
        return entry, kwargs

    def register(self, entry: ModelEntry, pair: Pair, kwargs: dict[str, Any], which: str = "") -> RegistrationResult:
        """``which``: the pair's place in a batch (``pairs[2]``), named in a failure."""
        assert entry.registrar is not None
        failed = f"registration failed for {which}" if which else "registration failed"
        try:
            result = entry.registrar.register(pair.source, pair.target, **kwargs)
        except np.linalg.LinAlgError:  # an SVD that does not converge: extreme or degenerate coordinates
            raise APIError(422, f"{failed}: the numerics did not converge (extreme coordinates?)") from None
        pose = np.concatenate([result.rotation.ravel(), result.translation])
        if not np.isfinite(pose).all():  # e.g. a degenerate cloud the checks let through
            raise APIError(422, f"{failed}: the pose is not finite (degenerate input?)")
        return result

    def register_one(self, pair: Pair, model: str | None = None) -> tuple[ModelEntry, RegistrationResult]:
        entry, kwargs = self.prepare(pair, model)
        return entry, self.register(entry, pair, kwargs)

    def register_batch(self, pairs: list[Pair]) -> list[tuple[ModelEntry, RegistrationResult]]:
        """All pairs are checked before the first one runs, so a bad pair costs no computation."""
        prepared = [self.prepare(pair, prefix=f"pairs[{i}].") for i, pair in enumerate(pairs)]
        return [(entry, self.register(entry, pair, kwargs, f"pairs[{i}]"))
                for i, (pair, (entry, kwargs)) in enumerate(zip(pairs, prepared, strict=True))]

    def observe(self, entry: ModelEntry, result: RegistrationResult, queue_ms: float) -> None:
        self.metrics.observe_timing(entry.name, {"queue": queue_ms, **result.timing_ms})
        self.metrics.observe_quality(entry.name, result.reliable, result.warnings)


# -- results -> response bodies ----------------------------------------------------------------------
def model_ref(entry: ModelEntry) -> dict[str, str]:
    registrar: Registrar = entry.registrar  # type: ignore[assignment]
    return {"name": entry.name, "version": registrar.manifest.version, "sha256": registrar.manifest.sha256}


def register_response(entry: ModelEntry, pair: Pair, result: RegistrationResult, queue_ms: float) -> dict[str, Any]:
    """The ``RegisterResponse`` body (plain floats: JSON keeps every float64 bit), keys in the model's
    field order and no ``None`` values, as ``response_model_exclude_none=True`` rendered it.

    ``ValueError`` (a 500) if a number breaks the response schema: NaN or infinity (JSON has none),
    credibility outside [0, 1] or a negative weight. FastAPI's response validation and
    ``json.dumps(allow_nan=False)`` refused such bodies before the routes rendered with orjson.
    """
    _check_response_numbers(result, queue_ms, pair.options)
    body: dict[str, Any] = pose_fields(result.rotation, result.translation)
    if pair.options.return_correspondences:
        body["correspondences"] = [
            {"source_index": s, "target_index": g, "credibility": c, "weight": w}
            for s, g, c, w in zip(
                result.source_index.tolist(),
                result.target_index.tolist(),
                result.credibility.tolist(),
                result.weight.tolist(),
                strict=True,
            )
        ]
    body.update({
        "quality": {
            "inlier_ratio": float(result.inlier_ratio),
            "residual_rms": float(result.residual_rms),
            "reliable": bool(result.reliable),
            "stability": None if result.stability is None else float(result.stability),
        },
        "warnings": list(result.warnings),
        "model": model_ref(entry),
        "iterations": int(result.iterations),
        "timing_ms": {"queue": float(queue_ms), **{k: float(v) for k, v in result.timing_ms.items()}},
    })
    if pair.options.return_iterations:
        body["iteration_poses"] = [
            {"rotation": p.rotation.tolist(), "translation": p.translation.tolist()} for p in result.iteration_poses
        ]
    return body


def _check_response_numbers(result: RegistrationResult, queue_ms: float, options: RegisterOptions) -> None:
    scalars = [result.inlier_ratio, result.residual_rms, queue_ms, *result.timing_ms.values()]
    scalars += [] if result.stability is None else [result.stability]
    arrays = [result.rotation, result.translation, np.asarray(scalars, dtype=np.float64)]
    ok = True
    if options.return_correspondences:
        credibility, weight = result.credibility, result.weight
        arrays += [credibility, weight]
        ok = bool(((credibility >= 0) & (credibility <= 1)).all() and (weight >= 0).all())
    if options.return_iterations:
        arrays += [a for pose in result.iteration_poses for a in (pose.rotation, pose.translation)]
    if not (ok and all(np.isfinite(a).all() for a in arrays)):
        raise ValueError("the registration result has numbers the response schema does not allow")

