"""The options ``mfgnet register`` and ``mfgnet sequence`` share: their declarations (help, ranges, defaults)
and their checks, turned into the registration options both pass on."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from service.cli.common import fail
from service.refine_modes import REFINE_POINTS_RANGE, SERVICE_DEFAULT_REFINE, Refine
from service.request_defaults import DEFAULT_MODEL, KEYPOINT_RANGE, MAX_ITERATIONS, THREAD_RANGE
from service.search_mode import RotationSearchMode, rotation_search_from_options

ModelDirs = Annotated[
    list[Path] | None,
    typer.Option("--model-dir", metavar="DIR", help="extra model folder, or a folder of model folders (repeatable)"),
]

ModelOpt = Annotated[
    str | None,
    typer.Option(
        help="in-process, a bundled model's name, one under --model-dir, or a model folder [default: "
        f"{DEFAULT_MODEL!r}; the only model under --model-dir where it holds one]; with --server, the "
        "name of a model the server serves [default: its MFGNET_DEFAULT_MODEL]"
    ),
]
IterationsOpt = Annotated[
    int | None, typer.Option(min=1, max=MAX_ITERATIONS, help="network iterations (default: the model's)")
]
KeypointsOpt = Annotated[
    int | None,
    typer.Option(min=KEYPOINT_RANGE[0], max=KEYPOINT_RANGE[1], help="keypoints K (default: the model's)"),
]
RefineOpt = Annotated[
    Refine | None,
    typer.Option(
        help="refine the network's pose: icp = point-to-point ICP, icp-plane = wide robust "
        "symmetric stage, then point-to-plane ICP (best for two independently sampled scans), "
        "icp-plane-multistart = icp-plane, then 12 turned restarts kept by a two-way fit (sparse "
        "clouds; 3.3-3.9x the refinement time, 1.8x a registration's), "
        "none = the network's pose alone, unrefined (or the initial transform where it fits better) "
        f"[default: {SERVICE_DEFAULT_REFINE} in-process, the server's MFGNET_DEFAULT_REFINE with --server]"
    ),
]
RefinePointsOpt = Annotated[
    int | None,
    typer.Option(
        min=REFINE_POINTS_RANGE[0],
        max=REFINE_POINTS_RANGE[1],
        help="points per cloud the refinement uses (more: a more precise pose on dense scans, slower; "
        "not with --refine none) [default: the network's working clouds, 768]",
    ),
]
DropIsolatedOpt = Annotated[
    bool, typer.Option(help="leave out isolated points (flying pixels, sparse clutter) before sampling the clouds")
]
ServerOpt = Annotated[
    str | None, typer.Option(help="register through a running service at this URL instead of in-process")
]
ApiKeyOpt = Annotated[str | None, typer.Option(envvar="MFGNET_API_KEY", help="API key for --server")]
TimeoutOpt = Annotated[
    float,
    typer.Option(
        min=1,
        help="with --server: seconds to wait for the answer (the server's "
        "deadline, MFGNET_TIMEOUT_S, starts once the upload is read)",
    ),
]
BusyRetriesOpt = Annotated[
    int,
    typer.Option(
        min=0,
        help="with --server: times to send the request again when the "
        "server answers 503 busy or still loading (with "
        "Retry-After), after the wait it asks for (at most 10 s, "
        "within --timeout); 0: fail at once",
    ),
]
RotationSearchOpt = Annotated[
    bool | None,
    typer.Option(
        help="always start from 24 rotations covering SO(3) (any relative orientation; 1.4-2.6x the "
        "time with a refinement, 7-15x without); = --rotation-search-mode on"
    ),
]
RotationSearchModeOpt = Annotated[
    RotationSearchMode | None,
    typer.Option(
        help="off: never search; on: always (= --rotation-search); auto: register plainly first and "
        "search only when that result looks wrong (low inlier ratio for the target's density), "
        "keeping the better of both; timing_ms then has a 'search' key [default: auto, off with --refine "
        "none; with --server the server's MFGNET_DEFAULT_ROTATION_SEARCH]"
    ),
]
ThreadsOpt = Annotated[
    int | None, typer.Option(min=THREAD_RANGE[0], max=THREAD_RANGE[1], help="ONNX Runtime threads (in-process)")
]


CLIENT_FLAGS = {"api_key": "--api-key", "binary": "--binary/--no-binary", "timeout": "--timeout",
                "busy_retries": "--busy-retries"}  # the command's parameters that only a --server run reads


def check_server_flags(server: str | None, model_dir: list[Path] | None, threads: int | None,
                       ctx: typer.Context | None = None) -> None:
    """Usage errors of ``--server``: a URL without its scheme, in-process options with it, or options of a server's
    client given on the command line without it (``ctx``: the command's; ``--api-key`` from ``MFGNET_API_KEY`` does not
    count)."""
    if not server and ctx is not None:
        for name, flag in CLIENT_FLAGS.items():
            source = ctx.get_parameter_source(name)
            if source is not None and source.name == "COMMANDLINE":
                fail(f"{flag} only applies with --server; an in-process run has no server to send it to")
    if server and model_dir:
        fail("--model-dir only applies in-process; a server uses its own model folders")
    if server and not server.lower().startswith(("http://", "https://")):
        fail(f"--server {server!r}: a URL starting with http:// or https://")
    if server and threads is not None:
        fail("--threads only applies in-process; a server uses its MFGNET_THREADS")


def registration_options(
    iterations: int | None,
    keypoints: int | None,
    refine: Refine | None,
    refine_points: int | None,
    drop_isolated: bool,
    rotation_search: bool | None,
    rotation_search_mode: RotationSearchMode | None,
) -> dict:
    """The registration options of the command line's flags, or a usage error where they contradict each other.
    ``refine`` and the search left unset stay ``None``: the server's defaults apply, in process the same ones
    (:class:`service.in_process.LocalRegistrar`); ``drop_isolated`` is sent only where it departs from the default."""
    if refine is not None and refine.value == "none" and refine_points is not None:
        fail("--refine-points sets the refinement's clouds; --refine none runs no refinement")
    try:
        search = rotation_search_from_options(rotation_search, rotation_search_mode)
    except ValueError as exc:
        fail(str(exc))
    options = {
        "iterations": iterations,
        "keypoints": keypoints,
        "refine": refine.value if refine is not None else None,
        "rotation_search": search,
        "refine_points": refine_points,
    }
    if not drop_isolated:
        options["drop_isolated"] = False
    return options
