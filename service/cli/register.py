"""``mfgnet register``: one pair, in process or through a running service, printed or written as JSON, and the
source written moved onto the target."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from service.cli.common import (
    UNRELIABLE_EXIT,
    check_output_path,
    fail,
    number,
    read_cloud,
    same_file,
    write_aligned_cloud,
    write_text,
)
from service.cli.model_lookup import load_registrar
from service.cli.options import (
    ApiKeyOpt,
    BusyRetriesOpt,
    DropIsolatedOpt,
    IterationsOpt,
    KeypointsOpt,
    ModelDirs,
    ModelOpt,
    RefineOpt,
    RefinePointsOpt,
    RotationSearchModeOpt,
    RotationSearchOpt,
    ServerOpt,
    ThreadsOpt,
    TimeoutOpt,
    check_server_flags,
    registration_options,
)
from service.cli.records import ServerError, local_record, remote_record, server_client

SourceArg = Annotated[
    Path,
    typer.Argument(
        metavar="SOURCE", help="cloud to move (.ply .pcd .las .laz .e57 .xyz .txt .csv .pts .ptx .npy .npz)"
    ),
]
TargetArg = Annotated[Path, typer.Argument(metavar="TARGET", help="cloud to align it to (same formats)")]
InitialTransformOpt = Annotated[
    Path | None,
    typer.Option(
        help="initial source->target guess (T_target_source, e.g. from odometry): .json (a "
        "4x4 list, or a --out file), .npy 4x4 or .txt (4 rows of 4 numbers); kept where it fits "
        "better than the network's poses (with --refine none too, returned unrefined)"
    ),
]
OutOpt = Annotated[
    Path | None,
    typer.Option(help="write the pose, quality, model and timing as JSON here ('-': to standard output, as --json)"),
]
WriteAlignedOpt = Annotated[
    Path | None,
    typer.Option(
        help="write the source moved onto the target (R @ p + t), format from the extension (.ply .pcd .las .laz .e57 "
        ".xyz .txt .csv .pts .ptx .npy .npz): a PLY, PCD, LAS/LAZ, XYZ/CSV/TXT, PTS, PTX, NPY or NPZ source written "
        "in its own format is that file moved, its other fields kept (colours, intensity, faces, an array's other "
        "columns and arrays; normals rotated); "
        "otherwise x, y, z only; an E57 source written as .e57 keeps its scans, images and fields, each scan's and "
        "image's pose composed with the registration"
    ),
]
BinaryOpt = Annotated[
    bool,
    typer.Option(
        help="with --server: upload the clouds as float32 .npy files (file uploads take up "
        "to the server's MFGNET_MAX_FILE_POINTS, 2,000,000 by default), or "
        "with --no-binary as JSON, every float64 digit (MFGNET_MAX_POINTS, 200,000)"
    ),
]
RequireReliableOpt = Annotated[
    bool, typer.Option(help="exit 3 when the result is not quality.reliable (the outputs are still written)")
]
JsonOpt = Annotated[bool, typer.Option("--json", help="print the JSON record instead of the summary")]


def register_command(
    ctx: typer.Context,
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
    _check_register_flags(write_aligned, out, source)
    _check_outputs_spare_inputs(out, write_aligned, source, target, initial_transform)
    check_server_flags(server, model_dir, threads, ctx)
    options = registration_options(
        iterations, keypoints, refine, refine_points, drop_isolated, rotation_search, rotation_search_mode
    )
    src, tgt = read_cloud(source), read_cloud(target)
    options["initial_transform"] = _read_transform(initial_transform) if initial_transform is not None else None
    if server:
        record = _register_remote(server, api_key, src, tgt, model, options, binary, timeout, busy_retries)
    else:
        record = _register_local(src, tgt, model, model_dir or [], threads, options,
                                 initial_transform.name if initial_transform is not None else None)
    _write_outputs(record, src, out, write_aligned, source)
    typer.echo(json.dumps(record, indent=2) if json_output else _summary(record, cloud_size(src)))
    if require_reliable and not record["quality"].get("reliable"):
        typer.echo("mfgnet: the result is not reliable (--require-reliable)", err=True)
        raise typer.Exit(UNRELIABLE_EXIT)


def _check_register_flags(write_aligned: Path | None, out: Path | None = None, source: Path | None = None) -> None:
    """Usage errors of ``register``'s outputs, before the registration runs: among them a LAS/LAZ, PTS or PTX
    ``--write-aligned`` of a source of another format (its format from its content), and a source written in its own
    format that its header says cannot be (:func:`service.cli.common.check_aligned_source`: an E57 file whose XML
    section cannot be rewritten, an ``.npy`` or ``.npz`` array the writer refuses)."""
    from service.cli.common import check_aligned_source
    from service.formats.moved import FORMAT_NAMES, OWN_FORMAT_ONLY, source_format
    from service.pointcloud_io import SUFFIXES

    check_output_path(out, "--out")
    check_output_path(write_aligned, "--write-aligned")
    if write_aligned is None:
        return
    suffix = write_aligned.suffix.lower()
    if suffix not in (*SUFFIXES, *OWN_FORMAT_ONLY):
        fail(
            f"--write-aligned {write_aligned}: unknown extension {write_aligned.suffix!r}; expected one of "
            f"{' '.join((*SUFFIXES, *OWN_FORMAT_ONLY))}"
        )
    kind = source_format(source) if source is not None else None
    own = OWN_FORMAT_ONLY.get(suffix)
    article = "an" if own == "e57" else "a"
    if own is not None and kind is not None and kind != own:
        fail(
            f"--write-aligned {write_aligned.name}: {article} {FORMAT_NAMES[own]} file is written only from {article} "
            f"{FORMAT_NAMES[own]} source; {source.name} is {FORMAT_NAMES[kind]} (write one of {' '.join(SUFFIXES)})"
        )
    if source is not None:
        check_aligned_source(source, write_aligned.name)


def _check_outputs_spare_inputs(out: Path | None, write_aligned: Path | None, source: Path, target: Path,
                                initial_transform: Path | None) -> None:
    """Usage errors where ``--out`` and ``--write-aligned`` name the same file, or one of them names an input
    (SOURCE, TARGET, ``--initial-transform``): it would be overwritten."""
    if out is not None and write_aligned is not None and same_file(out, write_aligned):
        fail(f"--out and --write-aligned are the same file, {out}")
    inputs = {"SOURCE": source, "TARGET": target, "--initial-transform": initial_transform}
    for path, option in ((out, "--out"), (write_aligned, "--write-aligned")):
        for label, named in inputs.items():
            if path is not None and named is not None and same_file(path, named):
                fail(f"{option} {path} is the {label} file; it would be overwritten")


def _write_outputs(
    record: dict, src: np.ndarray, out: Path | None, write_aligned: Path | None, source: Path | None = None
) -> None:
    """``--out`` (the JSON record) and ``--write-aligned`` (the source moved by the pose: the ``source`` file itself,
    moved, where the output's format is its own (:data:`service.formats.moved.KEPT_FORMATS`), else ``src``'s x, y, z
    moved)."""
    R = np.asarray(record["rotation"], dtype=np.float64)  # [3, 3]
    t = np.asarray(record["translation"], dtype=np.float64)  # [3]
    if out is not None:
        write_text(out, json.dumps(record, indent=2) + "\n")
        typer.echo(f"wrote {out}", err=True)
    if write_aligned is not None:
        write_aligned_cloud(write_aligned, source, src, R, t)


def _read_transform(path: Path) -> list:
    """``--initial-transform``'s 4x4 matrix (:func:`service.transform_file.read_transform`), or a usage error."""
    from service.transform_file import TransformFileError, read_transform

    try:
        return read_transform(path).tolist()
    except TransformFileError as exc:
        fail(f"--initial-transform {path.name}: {exc}")


def _register_local(
    src: np.ndarray, tgt: np.ndarray, model: str | None, model_dirs: list[Path], threads: int | None, options: dict,
    transform_name: str | None = None,
) -> dict:
    """The record of ``src`` registered onto ``tgt`` in this process, as :class:`service.in_process.LocalRegistrar`
    registers (the service's defaults for the options left ``None``); ``transform_name``: the ``--initial-transform``
    file's name, for the pipeline's complaints about its matrix."""
    from service.errors import InputError

    registrar = load_registrar(model, model_dirs, threads)
    try:
        return local_record(registrar, src, tgt, options)
    except InputError as exc:
        message = str(exc)
        if transform_name is not None and message.startswith("initial_transform "):  # the option's, as the flag's
            message = f"--initial-transform {transform_name}: {message.removeprefix('initial_transform ')}"
        fail(message)


def _register_remote(
    server: str,
    api_key: str | None,
    src: np.ndarray,
    tgt: np.ndarray,
    model: str | None,
    options: dict,
    binary: bool,
    timeout: float,
    busy_retries: int,
) -> dict:
    """The pose from ``server``; the float64 clouds go to the client as they are (it re-centres far-away ones before
    any float32 upload: cast here, map coordinates lost their centimetres, and the pose its degrees)."""
    with server_client(server, api_key, timeout, busy_retries) as client:
        try:
            return remote_record(client, src, tgt, model, options, binary)
        except ServerError as exc:
            fail(str(exc), code=exc.code)


def summary_decimals(T: np.ndarray, size: float | None = None) -> int:
    """Decimals that print the pose ``T [4, 4]`` closely enough to apply: 6, and one more per digit of its largest
    translation above 1 (a pose about a far origin, such as map coordinates 4e6 m out, turns points metres away from
    a rotation rounded to 6 decimals); for clouds of ``size`` (the source's RMS radius) below 1e-3 of their unit (a
    part in kilometres), one more per digit of that size below 1. A translation that is only rounding noise (a cloud
    onto itself) adds none."""
    reach = float(np.abs(T[:3, 3]).max())
    if 1.0 < reach < np.inf:
        return min(17, 6 + int(np.ceil(np.log10(reach))))
    if size is not None and 0.0 < size < 1e-3:  # clouds small in their unit: their size, not the translation's noise
        return min(17, 6 + int(np.ceil(-np.log10(size))))
    return 6


def cloud_size(src: np.ndarray) -> float | None:
    """The RMS radius of ``src [N, 3]``'s finite rows, from at most about 100,000 of them (the summary's digits)."""
    from service.normalization import rms_radius

    sample = src[:: max(1, len(src) // 100_000)]  # [<=~100,000, 3]: the size of the cloud, not every row of it
    finite = sample[np.isfinite(sample).all(axis=1)]
    return rms_radius(finite) if len(finite) else None


def warning_lines(warnings: list[str]) -> list[str]:
    """The summary's warnings, one per line (a warning's own text may hold "; "), ``none`` where there is none."""
    if not warnings:
        return ["warnings     none"]
    return [f"warnings     {warnings[0]}", *(f"             {warning}" for warning in warnings[1:])]


def _summary(record: dict, size: float | None = None) -> str:
    T = np.asarray(record["transform"])
    matrix = np.array2string(T, precision=summary_decimals(T, size), suppress_small=True, floatmode="fixed", sign=" ",
                             max_line_width=400)
    model, quality = record["model"], record["quality"]
    total = record["timing_ms"].get("total")
    lines = [
        "transform (source -> target):",
        *("  " + line.strip() for line in matrix.replace("[[", "[").replace("]]", "]").splitlines()),
        f"model        {model.get('name', '?')} {model.get('version', '')}".rstrip(),
        f"inlier ratio {number(quality.get('inlier_ratio'))}   residual rms {number(quality.get('residual_rms'))}",
        f"reliable     {'yes' if quality.get('reliable') else 'no'}   stability {number(quality.get('stability'))}",
        *warning_lines(record["warnings"]),
        f"total        {number(total, '.1f')} ms",
    ]
    return "\n".join(lines)
