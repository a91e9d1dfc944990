"""``mfgnet serve``: the HTTP service, with settings from ``MFGNET_*`` variables and these options over them."""

from __future__ import annotations

from typing import Annotated

import typer

from service.cli.common import SERVE_EXTRA_HINT, fail
from service.cli.options import ModelDirs


def serve_command(
    host: Annotated[str | None, typer.Option(help="interface to bind (env MFGNET_HOST)")] = None,
    port: Annotated[int | None, typer.Option(help="TCP port (env MFGNET_PORT)")] = None,
    model_dir: ModelDirs = None,
    threads: Annotated[
        int | None, typer.Option(min=1, max=64, help="ONNX Runtime threads per model (env MFGNET_THREADS)")
    ] = None,
) -> None:
    """Run the HTTP service (POST /v1/register, GET /v1/models, GET /v2/health/ready).

    Settings come from MFGNET_* environment variables; options given here override them.
    """
    try:
        from service.api.app import run_server
        from service.api.registry import UnknownModelsError
        from service.core.config import Settings
    except ImportError as exc:
        fail(f"{SERVE_EXTRA_HINT} ({exc})")
    overrides = {
        "host": host,
        "port": port,
        "threads": threads,
        "model_dirs": [str(d) for d in model_dir] if model_dir else None,
    }
    try:
        settings = Settings(**{key: value for key, value in overrides.items() if value is not None})
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        fail(f"invalid settings: {exc}")
    try:
        run_server(settings)
    except UnknownModelsError as exc:  # raised while the app is made, before it serves
        fail(str(exc))
