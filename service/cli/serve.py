"""``mfgnet serve``: the HTTP service, with settings from ``MFGNET_*`` variables and these options over them."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from service.cli.common import SERVE_EXTRA_HINT, fail
from service.cli.model_lookup import holds_no_model
from service.cli.options import ModelDirs
from service.request_defaults import THREAD_RANGE

if TYPE_CHECKING:
    from pydantic import ValidationError


def serve_command(
    host: Annotated[str | None, typer.Option(help="interface to bind (env MFGNET_HOST)")] = None,
    port: Annotated[int | None, typer.Option(help="TCP port (env MFGNET_PORT)")] = None,
    model_dir: ModelDirs = None,
    threads: Annotated[
        int | None,
        typer.Option(
            min=THREAD_RANGE[0], max=THREAD_RANGE[1], help="ONNX Runtime threads per model (env MFGNET_THREADS)"
        ),
    ] = None,
) -> None:
    """Run the HTTP service (POST /v1/register, GET /v1/models, GET /v2/health/ready).

    Settings come from MFGNET_* environment variables; options given here override them.
    """
    try:
        from pydantic import ValidationError

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
    given = {key: value for key, value in overrides.items() if value is not None}
    try:
        settings = Settings(**given)
    except ValidationError as exc:
        fail(f"invalid settings: {settings_problems(exc, given)}")
    try:  # before the models load: a process leaving while ONNX Runtime builds a session aborts
        socket.getaddrinfo(settings.host, settings.port)
    except socket.gaierror as exc:
        fail(f"MFGNET_HOST / --host {settings.host!r}: {exc.strerror}")
    missing = [str(folder) for folder in settings.model_dirs if not Path(folder).is_dir()]
    if missing:
        fail(f"model folder{'s' * (len(missing) > 1)} {', '.join(missing)}: not a folder (--model-dir or "
             "MFGNET_MODEL_DIRS)")
    empty = [str(folder) for folder in settings.model_dirs if holds_no_model(Path(folder))]
    if empty:  # an empty or mis-mounted volume: it would serve no model, without a word
        fail(f"model folder{'s' * (len(empty) > 1)} {', '.join(empty)}: no model in it (a manifest.json or .onnx "
             "files, in it or in its subfolders; --model-dir or MFGNET_MODEL_DIRS)")
    if not settings.bundled_models and not settings.model_dirs:  # it would start, never be ready, and say nothing
        fail("no model to serve: MFGNET_BUNDLED_MODELS is false and MFGNET_MODEL_DIRS (--model-dir) names no folder")
    if (problem := temp_folder_problem()) is not None:  # every upload past 1 MiB and aligned answer would fail
        fail(problem)
    try:
        run_server(settings)
    except UnknownModelsError as exc:  # raised while the app is made, before it serves
        fail(str(exc))


def temp_folder_problem() -> str | None:
    """Why no temporary file can be written (``TMPDIR``, else ``/tmp``, missing or read-only: a read-only root
    filesystem without a ``/tmp`` volume), or ``None``."""
    import os
    import tempfile

    try:
        with tempfile.TemporaryFile() as probe:
            probe.write(b"\0")
    except OSError as exc:  # gettempdir() itself raises where no candidate folder is writable: not called again here
        folder = tempfile.tempdir or os.environ.get("TMPDIR") or "/tmp"
        return (f"no writable temporary folder ({folder}: {exc.strerror or exc}; TMPDIR, else /tmp): "
                "uploads past 1 MiB and aligned answers are written there; mount a writable volume on /tmp")
    return None


OPTION_OF = {"host": "--host", "port": "--port", "threads": "--threads", "model_dirs": "--model-dir"}


def settings_problems(exc: ValidationError, options: dict | None = None) -> str:
    """Each invalid setting of ``exc`` on one line's part: its environment variable (and its option where ``options``,
    the settings given as options, holds it), the problem and the value given (pydantic's own text adds a URL and
    error codes)."""
    options = options or {}
    return "; ".join(
        f"MFGNET_{str(error['loc'][0]).upper()}{''.join(f'[{part}]' for part in error['loc'][1:])}"
        f"{' / ' + OPTION_OF[error['loc'][0]] if error['loc'][0] in options else ''}: "
        f"{error['msg'].removeprefix('Value error, ')} "
        f"(got {'the value, not shown' if error['loc'][0] == 'api_key' else repr(error['input'])})"
        for error in exc.errors()
    )
