"""One pair's ``mfgnet register`` record, registered in process or through a running service (``--server``): the
pose, quality, warnings, model and timing, as the service's response gives them without correspondences."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from service.cli.common import SERVE_EXTRA_HINT, fail

if TYPE_CHECKING:  # onnxruntime and httpx load only in the commands that register
    from service.client import MfgnetClient
    from service.in_process import LocalRegistrar


def local_record(registrar: LocalRegistrar, src: np.ndarray, tgt: np.ndarray, options: dict) -> dict:
    """The ``mfgnet register`` record of ``src`` onto ``tgt`` by ``registrar``; raises
    :class:`service.errors.InputError` for a bad cloud or option."""
    result = registrar.register(src, tgt, **options)
    manifest = registrar.manifest
    return pose_record(
        result.rotation,
        result.translation,
        quality={
            "inlier_ratio": float(result.inlier_ratio),
            "residual_rms": float(result.residual_rms),
            "reliable": bool(result.reliable),
            "stability": None if result.stability is None else float(result.stability),
        },
        warnings=list(result.warnings),
        model={"name": manifest.name, "version": manifest.version, "sha256": manifest.sha256},
        iterations=int(result.iterations),
        timing_ms={key: round(float(value), 3) for key, value in result.timing_ms.items()},
    )


class ServerError(Exception):
    """A registration through ``--server`` that failed, with the exit status it means: ``code`` 2 where the server
    refused the request, 1 where no answer came, a 5xx or an answer without a pose (``mfgnet sequence`` adds which
    frames it was)."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


@contextlib.contextmanager
def server_client(server: str, api_key: str | None, timeout: float, busy_retries: int) -> Iterator[MfgnetClient]:
    """The :class:`service.client.MfgnetClient` of ``--server`` (one connection for every request made with it)."""
    try:
        from service.client import MfgnetClient
    except ImportError as exc:
        fail(f"--server needs httpx: {SERVE_EXTRA_HINT} ({exc})")
    try:
        client = MfgnetClient(server, api_key=api_key, timeout=timeout, busy_retries=busy_retries)
    except ValueError as exc:  # a key with a line break, a URL httpx cannot parse
        fail(str(exc).replace("base_url", "--server").replace("api_key", "--api-key"))
    with client:
        yield client


def remote_record(
    client: MfgnetClient, src: np.ndarray, tgt: np.ndarray, model: str | None, options: dict, binary: bool
) -> dict:
    """The ``mfgnet register`` record of ``src [N, 3]`` onto ``tgt [M, 3]`` from one ``POST /v1/register`` (no
    correspondences asked for); raises :class:`ServerError`."""
    from service.client import MfgnetError, pose_from_response

    try:
        response = client.register(src, tgt, model=model, return_correspondences=False, binary=binary, **options)
    except MfgnetError as exc:
        hint = " (--api-key or MFGNET_API_KEY)" if exc.status == 401 else ""
        message = str(exc).replace(": busy_retries=", ": --busy-retries ")  # why it gave up: the flag, not the keyword
        raise ServerError(f"server: {message}{hint}", code=2 if 400 <= exc.status < 500 else 1) from exc
    try:
        R, t = pose_from_response(response)
    except ValueError as exc:
        raise ServerError(f"server: unexpected answer ({exc})", code=1) from exc
    keys = ("quality", "warnings", "model", "iterations", "timing_ms")
    return pose_record(R, t, **{key: response.get(key) for key in keys})


def pose_record(
    rotation: np.ndarray,
    translation: np.ndarray,
    quality: dict | None,
    warnings: list | None,
    model: dict | None,
    iterations: int | None,
    timing_ms: dict | None,
) -> dict:
    """The JSON record of ``mfgnet register`` (the service's response without correspondences)."""
    from service.pose_json import pose_fields

    return {
        **pose_fields(rotation, translation),
        "quality": quality or {},
        "warnings": list(warnings or []),
        "model": model or {},
        "iterations": iterations,
        "timing_ms": timing_ms or {},
    }
