"""The ``mfgnet`` command. Runtime sub-commands (serve, register, sequence, models) live here; training-side ones
(train, evaluate, make-pairs, export, ...) come from the ``mfgnet.commands`` entry points, loaded only when run
(``service.cli_plugins``), so a runtime command never imports torch, ``model``, ``export`` or ``bench``.

Heavy runtime modules (onnxruntime, the HTTP stack) are imported inside the commands that need them,
so ``mfgnet --help`` stays fast and works with the base install.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn, TextIO

import numpy as np
import typer

from service.cli_plugins import PluginGroup
from service.refine_modes import REFINE_POINTS_RANGE, SERVICE_DEFAULT_REFINE, Refine
from service.request_defaults import DEFAULT_MODEL
from service.search_mode import RotationSearchMode, rotation_search_from_options

if TYPE_CHECKING:  # onnxruntime and httpx load only in the commands that register
    from service.client import MfgnetClient
    from service.in_process import LocalRegistrar
    from service.sequence import Step

app = typer.Typer(cls=PluginGroup, help="MFGNet point-cloud registration", no_args_is_help=True,
                  add_completion=False, rich_markup_mode=None)  # plain click help: flag names never cut at 80 columns

SERVE_EXTRA_HINT = "this command needs the runtime extra: pip install 'mfgnet[serve]'"
UNRELIABLE_EXIT = 3  # mfgnet register --require-reliable: registered, but quality.reliable is false
TRANSFORM_TEXT_BYTES = 1 << 16  # an --initial-transform .txt: 16 numbers with comments fit many times over
# What each bundled model is for, shown by `mfgnet models` (a manifest's own "description" wins). The table shows
# no accuracy figures: each manifest's are on that model's own validation pairs, not comparable across models.
MODEL_PURPOSES = {
    "general": "independently sampled scans",
    "clean": "paper protocol: shared points, clean",
    "noise": "paper protocol: shared points, noisy",
    "unseen": "paper protocol: categories 0-19 only",
}
MODELS_TABLE_WIDTH = 100


ModelDirs = Annotated[
    list[Path] | None,
    typer.Option("--model-dir", metavar="DIR",
                 help="extra model folder, or a folder of model folders (repeatable)"),
]


def _fail(message: str, code: int = 2) -> NoReturn:
    """Print ``message`` on stderr and exit with ``code`` (2: bad input or usage, 1: anything else)."""
    typer.echo(f"mfgnet: error: {message}", err=True)
    raise typer.Exit(code=code)


# ----------------------------------------------------------------------------------------- serve


@app.command("serve")
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
        _fail(f"{SERVE_EXTRA_HINT} ({exc})")
    overrides = {"host": host, "port": port, "threads": threads,
                 "model_dirs": [str(d) for d in model_dir] if model_dir else None}
    try:
        settings = Settings(**{key: value for key, value in overrides.items() if value is not None})
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        _fail(f"invalid settings: {exc}")
    try:
        run_server(settings)
    except UnknownModelsError as exc:  # raised while the app is made, before it serves
        _fail(str(exc))


# -------------------------------------------------------------------------------------- register


SourceArg = Annotated[
    Path, typer.Argument(metavar="SOURCE", help="cloud to move (.ply .pcd .las .laz .xyz .txt .csv .npy .npz)")
]
TargetArg = Annotated[Path, typer.Argument(metavar="TARGET", help="cloud to align it to (same formats)")]
ModelOpt = Annotated[
    str | None,
    typer.Option(help="in-process, a bundled model's name, one under --model-dir, or a model folder [default: "
                      f"{DEFAULT_MODEL!r}; the only model under --model-dir where it holds one]; with --server, the "
                      "name of a model the server serves [default: its MFGNET_DEFAULT_MODEL]"),
]
IterationsOpt = Annotated[int | None, typer.Option(help="network iterations (default: the model's)")]
KeypointsOpt = Annotated[int | None, typer.Option(help="keypoints K (default: the model's)")]
RefineOpt = Annotated[
    Refine | None,
    typer.Option(help="refine the network's pose: icp = point-to-point ICP, icp-plane = wide robust "
                      "symmetric stage, then point-to-plane ICP (best for two independently sampled scans), "
                      "icp-plane-multistart = icp-plane, then 12 turned restarts kept by a two-way fit (sparse "
                      "clouds; 4.0-5.5x the refinement time, about twice a registration's), "
                      f"none = the network's pose alone [default: {SERVICE_DEFAULT_REFINE} in-process, the "
                      "server's MFGNET_DEFAULT_REFINE with --server]"),
]
RefinePointsOpt = Annotated[
    int | None,
    typer.Option(min=REFINE_POINTS_RANGE[0], max=REFINE_POINTS_RANGE[1],
                 help="points per cloud the refinement uses (more: a more precise pose on dense scans, slower) "
                      "[default: the network's working clouds, 768]"),
]
DropIsolatedOpt = Annotated[
    bool, typer.Option(help="leave out isolated points (flying pixels, sparse clutter) before sampling the clouds")
]
InitialTransformOpt = Annotated[
    Path | None, typer.Option(help="initial source->target guess (T_target_source, e.g. from odometry): .json (a "
                              "4x4 list, or a --out file), .npy 4x4 or .txt (4 rows of 4 numbers); with a refinement, "
                              "kept where it fits better than the network's poses")
]
OutOpt = Annotated[Path | None, typer.Option(help="write the pose, quality, model and timing as JSON here ('-': to "
                                                  "standard output, as --json)")]
WriteAlignedOpt = Annotated[
    Path | None, typer.Option(help="write the source moved onto the target (R @ p + t); format from extension")
]
ServerOpt = Annotated[
    str | None, typer.Option(help="register through a running service at this URL instead of in-process")
]
ApiKeyOpt = Annotated[str | None, typer.Option(envvar="MFGNET_API_KEY", help="API key for --server")]
BinaryOpt = Annotated[bool, typer.Option(help="with --server: upload the clouds as .npy files (file uploads take up "
                                              "to the server's MFGNET_MAX_FILE_POINTS, 2,000,000 by default), or "
                                              "with --no-binary as JSON (MFGNET_MAX_POINTS, 200,000)")]
TimeoutOpt = Annotated[float, typer.Option(min=1, help="with --server: seconds to wait for the answer (the server's "
                                                      "deadline, MFGNET_TIMEOUT_S, starts once the upload is read)")]
BusyRetriesOpt = Annotated[int, typer.Option(min=0, help="with --server: times to send the request again when the "
                                                         "server answers 503 busy or still loading (with "
                                                         "Retry-After), after the wait it asks for (at most 10 s, "
                                                         "within --timeout); 0: fail at once")]
RequireReliableOpt = Annotated[bool, typer.Option(help="exit 3 when the result is not quality.reliable (the outputs "
                                                       "are still written)")]
RotationSearchOpt = Annotated[
    bool | None,
    typer.Option(help="always start from 24 rotations covering SO(3) (any relative orientation; 1.5-2.6x the "
                      "time with a refinement, 12-18x without); = --rotation-search-mode on"),
]
RotationSearchModeOpt = Annotated[
    RotationSearchMode | None,
    typer.Option(help="off: never search; on: always (= --rotation-search); auto: register plainly first and "
                      "search only when that result looks wrong (low inlier ratio for the target's density), "
                      "keeping the better of both; timing_ms then has a 'search' key [default: auto, off with --refine "
                      "none; with --server the server's MFGNET_DEFAULT_ROTATION_SEARCH]"),
]
ThreadsOpt = Annotated[int | None, typer.Option(min=1, max=64, help="ONNX Runtime threads (in-process)")]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the JSON record instead of the summary")]


@app.command("register")
def register_command(
    source: SourceArg,
    target: TargetArg,
    model: ModelOpt = None,
    model_dir: ModelDirs = None,
    iterations: IterationsOpt = None,
    keypoints: KeypointsOpt = None,
    refine: RefineOpt = None,
    refine_points: RefinePointsOpt = None,
    drop_isolated: DropIsolatedOpt = True,
    initial_transform: InitialTransformOpt = None,
    out: OutOpt = None,
    write_aligned: WriteAlignedOpt = None,
    server: ServerOpt = None,
    api_key: ApiKeyOpt = None,
    binary: BinaryOpt = True,
    timeout: TimeoutOpt = 60.0,
    busy_retries: BusyRetriesOpt = 2,
    rotation_search: RotationSearchOpt = None,
    rotation_search_mode: RotationSearchModeOpt = None,
    threads: ThreadsOpt = None,
    json_output: JsonOpt = False,
    require_reliable: RequireReliableOpt = False,
) -> None:
    """Register SOURCE onto TARGET and print the 4x4 source->target transform.

    Runs in-process on a bundled or --model-dir model, or through a running service with --server.

    \b
    Exit codes:
    0 done (whether or not quality.reliable; see --require-reliable);
    2 bad input (unreadable or invalid cloud, bad option, unknown model,
      refused by the server);
    1 other failures (model integrity, server unreachable or 5xx);
    3 with --require-reliable: registered, but not reliable.
    """
    if out == Path("-"):  # the record on standard output, nothing else there
        out, json_output = None, True
    _check_register_flags(write_aligned, out)
    _check_server_flags(server, model_dir, threads)
    if refine is not None and refine.value == "none" and refine_points is not None:
        _fail("--refine-points sets the refinement's clouds; --refine none runs no refinement")
    search = _search_option(rotation_search, rotation_search_mode)
    src, tgt = _read_cloud(source), _read_cloud(target)
    init = _read_transform(initial_transform) if initial_transform is not None else None
    # refine and rotation_search not given stay None: the server's defaults apply, in-process the same ones
    # (service.in_process.LocalRegistrar)
    options = {"iterations": iterations, "keypoints": keypoints, "refine": refine.value if refine is not None else None,
               "initial_transform": init, "rotation_search": search, "refine_points": refine_points}
    if not drop_isolated:  # sent only when it departs from the default
        options["drop_isolated"] = False
    if server:
        record = _register_remote(server, api_key, src, tgt, model, options, binary, timeout, busy_retries)
    else:
        record = _register_local(src, tgt, model, model_dir or [], threads, options)
    _write_outputs(record, src, out, write_aligned)
    typer.echo(json.dumps(record, indent=2) if json_output else _summary(record))
    if require_reliable and not record["quality"].get("reliable"):
        typer.echo("mfgnet: the result is not reliable (--require-reliable)", err=True)
        raise typer.Exit(UNRELIABLE_EXIT)


def _check_register_flags(write_aligned: Path | None, out: Path | None = None) -> None:
    """Usage errors of ``register``'s outputs, before the registration runs."""
    from service.pointcloud_io import SUFFIXES

    _check_output_path(out, "--out")
    _check_output_path(write_aligned, "--write-aligned")
    if write_aligned is not None and write_aligned.suffix.lower() not in SUFFIXES:
        _fail(f"--write-aligned {write_aligned.name}: unknown extension {write_aligned.suffix!r}; expected {SUFFIXES}")


def _check_server_flags(server: str | None, model_dir: list[Path] | None, threads: int | None) -> None:
    """Usage errors of ``--server`` (register, sequence): a URL without its scheme, or in-process options with it."""
    if server and model_dir:
        _fail("--model-dir only applies in-process; a server uses its own model folders")
    if server and not server.lower().startswith(("http://", "https://")):
        _fail(f"--server {server!r}: a URL starting with http:// or https://")
    if server and threads is not None:
        _fail("--threads only applies in-process; a server uses its MFGNET_THREADS")


def _check_output_path(path: Path | None, option: str) -> None:
    """A usage error where the output ``path`` of ``option`` is a folder or lies in a folder that does not exist."""
    if path is not None and path.is_dir():
        _fail(f"{option} {path}: a folder, not a file")
    if path is not None and not path.parent.is_dir():
        _fail(f"{option} {path}: folder {path.parent} does not exist")


def _search_option(flag: bool | None, mode: RotationSearchMode | None) -> bool | str | None:
    """``rotation_search`` from ``--[no-]rotation-search`` and ``--rotation-search-mode``, or a usage error."""
    try:
        return rotation_search_from_options(flag, mode)
    except ValueError as exc:
        _fail(str(exc))


def _require_regular_file(path: Path) -> None:
    """A usage error where ``path`` is a FIFO, a device or a socket: its ``open()`` could block for ever."""
    if path.exists() and not path.is_file() and not path.is_dir():
        _fail(f"cannot read {path}: not a regular file")


def _read_cloud(path: Path) -> np.ndarray:
    """``[N, 3]`` float64 points of ``path`` (any format :mod:`service.pointcloud_io` reads), or a usage error."""
    from service.pointcloud_io import PointCloudFormatError, read_points

    _require_regular_file(path)
    try:
        return read_points(path).astype(np.float64)
    except PointCloudFormatError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror or exc}")


def _write_outputs(record: dict, src: np.ndarray, out: Path | None, write_aligned: Path | None) -> None:
    """``--out`` (the JSON record) and ``--write-aligned`` (the source moved by the pose)."""
    from service.pointcloud_io import PointCloudFormatError, write_points

    R = np.asarray(record["rotation"], dtype=np.float64)  # [3, 3]
    t = np.asarray(record["translation"], dtype=np.float64)  # [3]
    if out is not None:
        _write_text(out, json.dumps(record, indent=2) + "\n")
        typer.echo(f"wrote {out}", err=True)
    if write_aligned is not None:
        try:
            write_points(write_aligned, src @ R.T + t)
        except (PointCloudFormatError, OSError) as exc:
            _fail(f"cannot write {write_aligned}: {exc}", code=1)
        typer.echo(f"wrote {write_aligned}", err=True)


def _read_transform(path: Path) -> list:
    """A 4x4 matrix from ``.json`` (a 4x4 list, or an object with ``transform``), ``.npy`` or ``.txt`` (four rows of
    four numbers, as ``np.savetxt`` and other registration tools write a pose; commas allowed, ``#`` comments)."""
    _require_regular_file(path)
    try:
        if path.suffix.lower() == ".json":
            payload = json.loads(path.read_text())
            matrix = payload.get("transform") if isinstance(payload, dict) else payload
            if matrix is None:
                _fail(f"--initial-transform {path.name}: JSON object has no 'transform' (expected a 4x4 list, or an "
                      "object with 'transform' as an --out file holds)")
            T = np.asarray(matrix, dtype=np.float64)
        elif path.suffix.lower() == ".npy":
            T = np.load(path, allow_pickle=False, mmap_mode="r")  # mapped: a header's shape allocates nothing
        elif path.suffix.lower() == ".txt":
            if path.stat().st_size > TRANSFORM_TEXT_BYTES:
                _fail(f"--initial-transform {path.name}: over {TRANSFORM_TEXT_BYTES} bytes, not a 4x4 matrix")
            rows = [line.split("#", 1)[0].replace(",", " ").split() for line in path.read_text().splitlines()]
            T = np.asarray([[float(value) for value in row] for row in rows if row], dtype=np.float64)  # [4, 4]
        else:
            _fail(f"--initial-transform {path.name}: expected a .json, .npy or .txt file")
        if not isinstance(T, np.ndarray) or T.shape != (4, 4):
            shape = list(T.shape) if isinstance(T, np.ndarray) else type(T).__name__
            _fail(f"--initial-transform {path.name}: expected a 4x4 matrix, got {shape}")
        T = np.asarray(T, dtype=np.float64)
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror or exc}")
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # not numbers, too deep, beyond float64
        _fail(f"--initial-transform {path.name}: not a 4x4 matrix ({type(exc).__name__}: {str(exc)[:200]})")
    return T.tolist()


def _register_local(src: np.ndarray, tgt: np.ndarray, model: str | None, model_dirs: list[Path], threads: int | None,
                    options: dict) -> dict:
    """The record of ``src`` registered onto ``tgt`` in this process, as :class:`service.in_process.LocalRegistrar`
    registers (the service's defaults for the options left ``None``)."""
    from service.errors import InputError

    registrar = _load_registrar(model, model_dirs, threads)
    try:
        return _local_record(registrar, src, tgt, options)
    except InputError as exc:
        _fail(str(exc))


def _load_registrar(model: str | None, model_dirs: list[Path], threads: int | None) -> LocalRegistrar:
    """The :class:`service.in_process.LocalRegistrar` of ``model`` (see :func:`_resolve_model_dir`), not warmed up;
    exit 1 when its files fail their check or ONNX Runtime refuses them."""
    try:
        from service.in_process import LocalRegistrar
        from service.manifest import ModelIntegrityError
    except ImportError as exc:
        _fail(f"{SERVE_EXTRA_HINT} ({exc})")
    directory = _resolve_model_dir(model, model_dirs)
    try:
        return LocalRegistrar(directory, threads=threads, warmup=False)
    except ModelIntegrityError as exc:
        _fail(str(exc), code=1)
    except Exception as exc:  # e.g. ONNX Runtime refusing a graph whose hash matches its manifest
        _fail(f"cannot load the model in {directory}: {exc}", code=1)


def _local_record(registrar: LocalRegistrar, src: np.ndarray, tgt: np.ndarray, options: dict) -> dict:
    """The ``mfgnet register`` record of ``src`` onto ``tgt`` by ``registrar``; raises
    :class:`service.errors.InputError` for a bad cloud or option."""
    result = registrar.register(src, tgt, **options)
    manifest = registrar.manifest
    return pose_record(
        result.rotation, result.translation,
        quality={"inlier_ratio": float(result.inlier_ratio), "residual_rms": float(result.residual_rms),
                 "reliable": bool(result.reliable),
                 "stability": None if result.stability is None else float(result.stability)},
        warnings=list(result.warnings),
        model={"name": manifest.name, "version": manifest.version, "sha256": manifest.sha256},
        iterations=int(result.iterations),
        timing_ms={key: round(float(value), 3) for key, value in result.timing_ms.items()},
    )


def _resolve_model_dir(model: str | None, model_dirs: list[Path]) -> Path:
    """The folder of ``model`` (a model's name, else a path); without a name: :func:`_default_model_dir`.
    Folders under ``--model-dir`` win over bundled ones of the same name; a name wins over a folder of that name in
    the working directory (a training run's ``--out runs/general`` beside it), unless written as a path (``./x``)."""
    from service.manifest import bundled_models_dir

    extra, bundled = _model_dirs(model_dirs)
    if model is None and len(extra) == 1:
        return extra[0]
    name = DEFAULT_MODEL if model is None else model
    for directory in [*extra, *bundled]:
        if directory.name == name:
            return directory
    if model is not None and Path(model).is_dir():
        return Path(model)
    names = sorted({d.name for d in [*extra, *bundled]})
    where = ", ".join(str(d) for d in [bundled_models_dir(), *model_dirs])
    _fail(f"model {name!r} not found in {where}; available: {', '.join(names) or 'none'}")


def _model_dirs(model_dirs: list[Path]) -> tuple[list[Path], list[Path]]:
    """``(the model folders under --model-dir that are not bundled, the bundled ones)``; a usage error where a
    ``--model-dir`` is not a folder (it was ignored)."""
    from service.manifest import discover_model_dirs

    missing = [str(d) for d in model_dirs if not d.is_dir()]
    if missing:
        _fail(f"--model-dir {missing[0]}: not a folder")
    bundled = discover_model_dirs([])
    return [d for d in discover_model_dirs(model_dirs) if d not in bundled], bundled


def _default_model_dir(model_dirs: list[Path]) -> Path | None:
    """What ``mfgnet register`` runs without ``--model``: the only model under ``--model-dir``, else the first
    folder named ``DEFAULT_MODEL`` (``--model-dir`` ones first); ``None`` when there is none."""
    extra, bundled = _model_dirs(model_dirs)
    if len(extra) == 1:
        return extra[0]
    return next((d for d in [*extra, *bundled] if d.name == DEFAULT_MODEL), None)


def _register_remote(server: str, api_key: str | None, src: np.ndarray, tgt: np.ndarray, model: str | None,
                     options: dict, binary: bool, timeout: float, busy_retries: int) -> dict:
    """The pose from ``server``; the float64 clouds go to the client as they are (it re-centres far-away ones before
    any float32 upload: cast here, map coordinates lost their centimetres, and the pose its degrees)."""
    with _server_client(server, api_key, timeout, busy_retries) as client:
        try:
            return _remote_record(client, src, tgt, model, options, binary)
        except ServerError as exc:
            _fail(str(exc), code=exc.code)


class ServerError(Exception):
    """A registration through ``--server`` that failed, with the exit status it means: ``code`` 2 where the server
    refused the request, 1 where no answer came, a 5xx or an answer without a pose (``mfgnet sequence`` adds which
    frames it was)."""

    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


@contextlib.contextmanager
def _server_client(server: str, api_key: str | None, timeout: float, busy_retries: int) -> Iterator[MfgnetClient]:
    """The :class:`service.client.MfgnetClient` of ``--server`` (one connection for every request made with it)."""
    try:
        from service.client import MfgnetClient
    except ImportError as exc:
        _fail(f"--server needs httpx: {SERVE_EXTRA_HINT} ({exc})")
    with MfgnetClient(server, api_key=api_key, timeout=timeout, busy_retries=busy_retries) as client:
        yield client


def _remote_record(client: MfgnetClient, src: np.ndarray, tgt: np.ndarray, model: str | None, options: dict,
                   binary: bool) -> dict:
    """The ``mfgnet register`` record of ``src [N, 3]`` onto ``tgt [M, 3]`` from one ``POST /v1/register`` (no
    correspondences asked for); raises :class:`ServerError`."""
    from service.client import MfgnetError, pose_from_response

    try:
        response = client.register(src, tgt, model=model, return_correspondences=False, binary=binary, **options)
    except MfgnetError as exc:
        hint = " (--api-key or MFGNET_API_KEY)" if exc.status == 401 else ""
        raise ServerError(f"server: {exc}{hint}", code=2 if 400 <= exc.status < 500 else 1) from exc
    try:
        R, t = pose_from_response(response)
    except ValueError as exc:
        raise ServerError(f"server: unexpected answer ({exc})", code=1) from exc
    keys = ("quality", "warnings", "model", "iterations", "timing_ms")
    return pose_record(R, t, **{key: response.get(key) for key in keys})


def pose_record(rotation: np.ndarray, translation: np.ndarray, quality: dict | None, warnings: list | None,
                model: dict | None, iterations: int | None, timing_ms: dict | None) -> dict:
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


def _summary(record: dict) -> str:
    T = np.asarray(record["transform"])
    matrix = np.array2string(T, precision=6, suppress_small=True, floatmode="fixed", sign=" ")
    model, quality = record["model"], record["quality"]
    total = record["timing_ms"].get("total")
    lines = [
        "transform (source -> target):",
        *("  " + line.strip() for line in matrix.replace("[[", "[").replace("]]", "]").splitlines()),
        f"model        {model.get('name', '?')} {model.get('version', '')}".rstrip(),
        f"inlier ratio {_number(quality.get('inlier_ratio'))}   residual rms {_number(quality.get('residual_rms'))}",
        f"reliable     {'yes' if quality.get('reliable') else 'no'}   stability {_number(quality.get('stability'))}",
        f"warnings     {'; '.join(record['warnings']) or 'none'}",
        f"total        {_number(total, '.1f')} ms",
    ]
    return "\n".join(lines)


def _number(value: float | None, spec: str = ".4g") -> str:
    return "?" if value is None else format(float(value), spec)


def _write_text(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        _fail(f"cannot write {path}: {exc.strerror or exc}", code=1)


# -------------------------------------------------------------------------------------- sequence


FramesArg = Annotated[
    list[Path], typer.Argument(metavar="FRAME", show_default=False,
                               help="two or more scans in order (.ply .pcd .las .laz .xyz .txt .csv .npy .npz); "
                                    "frame i is registered onto frame i-1")
]
SequenceOutOpt = Annotated[
    Path | None, typer.Option(help="write one JSON line per step here ('-': standard output, the default): index, "
                                   "source, target, the pair's `register --json` record, initial_transform and "
                                   "accumulated_transform (T_0_i)")
]
KittiOpt = Annotated[
    Path | None, typer.Option(help="write the accumulated poses T_0_i in the KITTI odometry format: one line per "
                                   "frame, frame 0's identity first, 12 numbers ([R|t] row-major)")
]
ConstantVelocityOpt = Annotated[
    bool, typer.Option(help="pass each step's relative pose as the next step's initial transform (the sensor "
                            "keeps moving as it moved; a result far from it carries a warning); without it no guess")
]
SequenceReliableOpt = Annotated[bool, typer.Option(help="exit 3 when any step is not quality.reliable (every step is "
                                                        "still written)")]


@app.command("sequence")
def sequence_command(
    frames: FramesArg,
    out: SequenceOutOpt = None,
    kitti: KittiOpt = None,
    constant_velocity: ConstantVelocityOpt = False,
    require_reliable: SequenceReliableOpt = False,
    model: ModelOpt = None,
    model_dir: ModelDirs = None,
    iterations: IterationsOpt = None,
    keypoints: KeypointsOpt = None,
    refine: RefineOpt = None,
    refine_points: RefinePointsOpt = None,
    drop_isolated: DropIsolatedOpt = True,
    server: ServerOpt = None,
    api_key: ApiKeyOpt = None,
    timeout: TimeoutOpt = 60.0,
    busy_retries: BusyRetriesOpt = 2,
    rotation_search: RotationSearchOpt = None,
    rotation_search_mode: RotationSearchModeOpt = None,
    threads: ThreadsOpt = None,
) -> None:
    """Register a sequence of scans: each FRAME onto the one before it.

    In one process with the model loaded once, or through a running service
    with --server (the frames read here and uploaded, one request per step).
    Each step gives the relative pose T_{i-1}_i (source frame i -> target
    frame i-1, as `mfgnet register` gives it) and the accumulated
    T_0_i = T_0_{i-1} @ T_{i-1}_i (frame i in frame 0's coordinates). Every
    frame is checked (exists, a regular file, a known extension) before the
    first registration; one short progress line per step goes to standard
    error. A path may repeat (a frame registered onto itself gives about the
    identity).

    \b
    Exit codes:
    0 done (whether or not every step is reliable; see --require-reliable);
    2 bad input (fewer than two frames, a missing or unreadable frame, a bad
      option, an unknown model, a step refused by the server); the steps
      before the frame that failed are written;
    1 other failures (model integrity, an output that cannot be written,
      server unreachable or 5xx);
    3 with --require-reliable: every step registered, one or more not reliable.
    """
    from service.sequence import frame_problem, register_sequence

    if out == Path("-"):
        out = None
    if len(frames) < 2:
        _fail(f"a sequence needs at least two frames, got {len(frames)}")
    for index, path in enumerate(frames):
        problem = frame_problem(path)
        if problem:
            _fail(f"frame {index} {path}: {problem}")
    _check_sequence_outputs(frames, out, kitti)
    _check_server_flags(server, model_dir, threads)
    if refine is not None and refine.value == "none" and refine_points is not None:
        _fail("--refine-points sets the refinement's clouds; --refine none runs no refinement")
    search = _search_option(rotation_search, rotation_search_mode)
    options = {"iterations": iterations, "keypoints": keypoints, "refine": refine.value if refine is not None else None,
               "rotation_search": search, "refine_points": refine_points}
    if not drop_isolated:
        options["drop_isolated"] = False
    with contextlib.ExitStack() as stack:
        if server:  # one connection for every step; .npy uploads, as register's default --binary
            client = stack.enter_context(_server_client(server, api_key, timeout, busy_retries))

            def register_pair(src: np.ndarray, tgt: np.ndarray, guess: list | None) -> dict:
                return _remote_record(client, src, tgt, model, {**options, "initial_transform": guess}, True)
        else:
            registrar = _load_registrar(model, model_dir or [], threads)

            def register_pair(src: np.ndarray, tgt: np.ndarray, guess: list | None) -> dict:
                return _local_record(registrar, src, tgt, {**options, "initial_transform": guess})

        steps = register_sequence(frames, _read_frame, register_pair, constant_velocity=constant_velocity)
        unreliable = _write_steps(steps, frames, out, kitti)
    written = ", ".join(str(path) for path in (out, kitti) if path is not None)
    typer.echo(f"{len(frames) - 1} steps, {len(unreliable)} not reliable" + (f"; wrote {written}" if written else ""),
               err=True)
    if require_reliable and unreliable:
        which = f"step{'s' if len(unreliable) > 1 else ''} {', '.join(map(str, unreliable))}"
        typer.echo(f"mfgnet: {which} not reliable (--require-reliable)", err=True)
        raise typer.Exit(UNRELIABLE_EXIT)


def _write_steps(steps: Iterator[Step], frames: list[Path], out: Path | None, kitti: Path | None) -> list[int]:
    """Each step's JSON line (``out``, else standard output), KITTI line (``kitti``) and progress line as it comes;
    the indices of the steps that are not quality.reliable."""
    from service.sequence import kitti_line

    unreliable: list[int] = []
    with _open_output(out) as lines, _open_output(kitti, to_stdout=False) as poses:
        if poses is not None:
            _write_line(poses, kitti_line(np.eye(4)), kitti)  # frame 0: the origin of the map
        for step in _steps_or_fail(steps, frames):
            _write_line(lines, step.json_line(), out)
            if poses is not None:
                _write_line(poses, kitti_line(step.accumulated), kitti)
            typer.echo(_step_progress(step, len(frames) - 1), err=True)
            if not step.reliable:
                unreliable.append(step.index)
    return unreliable


def _check_sequence_outputs(frames: list[Path], out: Path | None, kitti: Path | None) -> None:
    """Usage errors of ``--out`` and ``--kitti`` before any registration: a folder, a missing folder, the same file
    twice, or one of the frames (it would be overwritten)."""
    _check_output_path(out, "--out")
    _check_output_path(kitti, "--kitti")
    if kitti == Path("-"):
        _fail("--kitti -: standard output holds the JSON lines; name a file")
    if out is not None and kitti is not None and out.resolve() == kitti.resolve():
        _fail(f"--out and --kitti are the same file, {out}")
    inputs = {frame.resolve() for frame in frames}
    for path, option in ((out, "--out"), (kitti, "--kitti")):
        if path is not None and path.resolve() in inputs:
            _fail(f"{option} {path} is one of the frames; it would be overwritten")


def _read_frame(index: int, path: Path) -> np.ndarray:
    """``[N, 3]`` float64 points of frame ``index``, or exit 2 naming the frame."""
    from service.pointcloud_io import PointCloudFormatError, read_points

    try:
        return read_points(path).astype(np.float64)
    except PointCloudFormatError as exc:
        _fail(f"frame {index} {path}: {exc}")
    except OSError as exc:
        _fail(f"frame {index} {path}: cannot read it: {exc.strerror or exc}")


def _steps_or_fail(steps: Iterator[Step], frames: list[Path]) -> Iterator[Step]:
    """``steps`` as they come; a pair the pipeline or the server refuses (too few points, ...) is exit 2 naming both
    frames, a server unreachable or failing exit 1 naming them too."""
    from service.errors import InputError

    index = 1  # the step being registered: frame index onto frame index - 1
    while True:
        try:
            step = next(steps)
        except StopIteration:
            return
        except (InputError, ServerError) as exc:
            _fail(f"frame {index} {frames[index]} onto frame {index - 1} {frames[index - 1]}: {exc}",
                  code=exc.code if isinstance(exc, ServerError) else 2)
        yield step
        index += 1


@contextlib.contextmanager
def _open_output(path: Path | None, to_stdout: bool = True) -> Iterator[TextIO | None]:
    """``path`` opened for writing (exit 1 where it cannot be); without a path standard output, or ``None`` where
    ``to_stdout`` is false."""
    if path is None:
        yield sys.stdout if to_stdout else None
        return
    try:
        handle = path.open("w")
    except OSError as exc:
        _fail(f"cannot write {path}: {exc.strerror or exc}", code=1)
    with handle:
        yield handle


def _write_line(handle: TextIO, line: str, path: Path | None) -> None:
    """``line`` and a newline, flushed at once: a long run's steps can be followed, and survive a later failure."""
    try:
        handle.write(line + "\n")
        handle.flush()
    except OSError as exc:
        _fail(f"cannot write {path or 'standard output'}: {exc.strerror or exc}", code=1)


def _step_progress(step: Step, count: int) -> str:
    """One short line per step for standard error: the pair, reliable or not, the turn, the shift and the time."""
    turn = np.degrees(2 * np.arccos(min(1.0, abs(step.record["quaternion_xyzw"][3]))))
    shift = float(np.linalg.norm(step.record["translation"]))
    total = step.record["timing_ms"].get("total")
    state = "reliable" if step.reliable else "NOT reliable"
    return (f"[{step.index}/{count}] {step.source.name} -> {step.target.name}: {state}, turn {turn:.2f} deg, "
            f"shift {shift:.4g}, {_number(total, '.0f')} ms")


# ---------------------------------------------------------------------------------------- models


@app.command("models")
def models_command(
    model_dir: ModelDirs = None,
    json_output: Annotated[bool, typer.Option("--json", help="print a JSON list instead of the table")] = False,
) -> None:
    """List the bundled (and --model-dir) models: name, version, what each is for; * marks the default.

    Every model's files are checked against its manifest's sha256;
    models that fail are listed with the reason. Exit code 1 when no usable model is found.
    """
    from service.manifest import discover_model_dirs

    default = _default_model_dir(model_dir or [])
    entries = [_model_entry(directory, directory == default) for directory in discover_model_dirs(model_dir or [])]
    if json_output:
        typer.echo(json.dumps(entries, indent=2))
    else:
        typer.echo(_models_table(entries))
    if not any(entry["status"] == "ok" for entry in entries):
        raise typer.Exit(code=1)


def _model_entry(directory: Path, default: bool) -> dict:
    """One model folder as ``mfgnet models --json`` lists it (``status`` ``ok`` or ``failed`` with ``error``)."""
    from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest

    try:
        manifest = load_manifest(directory)
    except ModelIntegrityError as exc:
        return {"name": directory.name, "status": "failed", "error": str(exc), "directory": str(directory)}
    description = manifest.raw.get("description")
    return {
        "name": manifest.name,
        "status": "ok",
        "default": default,
        "version": manifest.version,
        "purpose": description if isinstance(description, str) else MODEL_PURPOSES.get(manifest.name),
        "iterations": manifest.config.get("iterations"),
        "keypoints": manifest.config.get("keypoints"),
        "size_bytes": sum(path.stat().st_size for path in manifest.graphs.values()),
        "bundled": directory.parent == bundled_models_dir(),
        "accuracy": manifest.accuracy,  # on the model's own evaluation pairs (see MODEL_PURPOSES)
        "sha256": manifest.sha256,
        "directory": str(directory),
    }


def _models_table(entries: list[dict]) -> str:
    """The table of ``mfgnet models``: at most ``MODELS_TABLE_WIDTH`` columns (long folders elided)."""
    if not entries:
        return "no models found"
    ok = [e for e in entries if e["status"] == "ok"]
    rows = [("", "NAME", "VERSION", "ITER", "K", "GRAPHS", "FOR", "WHERE")]
    rows += [("*" if e["default"] else "", e["name"], e["version"], str(e["iterations"]), str(e["keypoints"]),
              f"{e['size_bytes'] / 2**20:.1f} MiB", e["purpose"] or "-", "bundled" if e["bundled"] else e["directory"])
             for e in ok]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    room = MODELS_TABLE_WIDTH - sum(widths) - 2 * (len(widths) - 1) - 1
    lines = [_models_row(row, widths, room) for row in rows] if ok else []
    if any(e["default"] for e in ok):
        lines.append("* the default: what `mfgnet register` runs without --model (a server: MFGNET_DEFAULT_MODEL)")
    lines += [_elide(f"FAILED {e['name']}: {e['error']}", MODELS_TABLE_WIDTH) for e in entries if e["status"] != "ok"]
    return "\n".join(lines)


def _models_row(row: tuple[str, ...], widths: list[int], room: int) -> str:
    cells = [cell.ljust(width) for cell, width in zip(row[:-1], widths, strict=True)]
    return (cells[0] + " " + "  ".join(cells[1:]) + "  " + _elide(row[-1], room, left=True)).rstrip()


def _elide(text: str, width: int, left: bool = False) -> str:
    """``text`` cut to ``width`` characters with ``...`` (at the start when ``left``: a path's tail names it)."""
    if len(text) <= width:
        return text
    return "..." + text[len(text) - width + 3:] if left else text[: width - 3] + "..."


def main() -> None:
    app()


if __name__ == "__main__":
    main()
