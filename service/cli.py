"""The ``mfgnet`` command. Runtime sub-commands (serve, register, models) live here; training-side ones
(train, evaluate, make-pairs, export, ...) are discovered through the ``mfgnet.commands`` entry-point
group, so this module never imports torch, ``model`` or ``export``.

Heavy runtime modules (onnxruntime, the HTTP stack) are imported inside the commands that need them,
so ``mfgnet --help`` stays fast and works with the base install.
"""

from __future__ import annotations

import json
from importlib.metadata import entry_points
from importlib.util import find_spec
from pathlib import Path
from typing import Annotated, NoReturn

import numpy as np
import typer

from service.refine_modes import REFINE_POINTS_RANGE, SERVICE_DEFAULT_REFINE, Refine
from service.search_mode import RotationSearchMode, rotation_search_from_options, service_rotation_search

app = typer.Typer(help="MFGNet point-cloud registration", no_args_is_help=True, add_completion=False)

TRAIN_EXTRA_HINT = "this command needs the training side: pip install 'mfgnet[train]'"
SERVE_EXTRA_HINT = "this command needs the runtime extra: pip install 'mfgnet[serve]'"
DEFAULT_MODEL = "general"  # trained for independently sampled scans; clean/unseen reproduce the paper
ACCURACY_KEYS = ("rmse_r", "mae_r", "rmse_t", "mae_t", "recall_r5_t005")  # shown first by `mfgnet models`


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
        int | None, typer.Option(min=1, help="ONNX Runtime threads per model (env MFGNET_THREADS)")
    ] = None,
) -> None:
    """Run the HTTP service (POST /v1/register, GET /v1/models, GET /v2/health/ready).

    Settings come from MFGNET_* environment variables; options given here override them.
    """
    try:
        from service.api.app import run_server
        from service.core.config import Settings
    except ImportError as exc:
        _fail(f"{SERVE_EXTRA_HINT} ({exc})")
    overrides = {"host": host, "port": port, "threads": threads,
                 "model_dirs": [str(d) for d in model_dir] if model_dir else None}
    try:
        settings = Settings(**{key: value for key, value in overrides.items() if value is not None})
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        _fail(f"invalid settings: {exc}")
    run_server(settings)


# -------------------------------------------------------------------------------------- register


@app.command("register")
def register_command(
    source: Annotated[
        Path, typer.Argument(metavar="SOURCE", help="cloud to move (.ply .pcd .xyz .txt .csv .npy .npz)")
    ],
    target: Annotated[Path, typer.Argument(metavar="TARGET", help="cloud to align it to (same formats)")],
    model: Annotated[
        str | None,
        typer.Option(help=f"model name (bundled or under --model-dir) or a model folder; default {DEFAULT_MODEL!r} "
                          "in-process, the server's default with --server"),
    ] = None,
    model_dir: ModelDirs = None,
    iterations: Annotated[int | None, typer.Option(help="network iterations (default: the model's)")] = None,
    keypoints: Annotated[int | None, typer.Option(help="keypoints K (default: the model's)")] = None,
    refine: Annotated[
        Refine | None,
        typer.Option(help="refine the network's pose: icp = point-to-point ICP, icp-plane = wide robust "
                          "symmetric stage, then point-to-plane ICP (best for two independently sampled scans), "
                          "icp-plane-multistart = icp-plane, then 12 turned restarts kept by a two-way fit (sparse "
                          "clouds; ~2x the refinement time), "
                          f"none = the network's pose alone [default: {SERVICE_DEFAULT_REFINE} in-process, the "
                          "server's MFGNET_DEFAULT_REFINE with --server]"),
    ] = None,
    refine_points: Annotated[
        int | None,
        typer.Option(min=REFINE_POINTS_RANGE[0], max=REFINE_POINTS_RANGE[1],
                     help="points per cloud the refinement uses (more: a more precise pose on dense scans, slower) "
                          "[default: the network's working clouds, 768]"),
    ] = None,
    drop_isolated: Annotated[
        bool,
        typer.Option(help="leave out isolated points (flying pixels, sparse clutter) before sampling the clouds"),
    ] = True,
    initial_transform: Annotated[
        Path | None,
        typer.Option(help="initial source->target guess: .json (a 4x4 list, or a --out file) or .npy 4x4"),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="write the pose, quality, model and timing as JSON here")] = None,
    write_aligned: Annotated[
        Path | None, typer.Option(help="write the source moved onto the target (R @ p + t); format from extension")
    ] = None,
    server: Annotated[
        str | None, typer.Option(help="register through a running service at this URL instead of in-process")
    ] = None,
    api_key: Annotated[str | None, typer.Option(envvar="MFGNET_API_KEY", help="API key for --server")] = None,
    binary: Annotated[bool, typer.Option(help="with --server: upload the clouds as .npy files, not JSON")] = False,
    rotation_search: Annotated[
        bool | None,
        typer.Option(help="always start from 24 rotations covering SO(3) (any relative orientation; about 2-3x the "
                          "time with a refinement, 10-20x without); "
                          "= --rotation-search-mode on"),
    ] = None,
    rotation_search_mode: Annotated[
        RotationSearchMode | None,
        typer.Option(help="off: never search; on: always (= --rotation-search); auto: register plainly first and "
                          "search only when that result looks wrong (low inlier ratio for the target's density), "
                          "keeping the better of both; timing_ms then has a 'search' key [default: off; with "
                          "--server the server's MFGNET_DEFAULT_ROTATION_SEARCH]"),
    ] = None,
    threads: Annotated[int | None, typer.Option(min=1, help="ONNX Runtime threads (in-process)")] = None,
    json_output: Annotated[bool, typer.Option("--json", help="print the JSON record instead of the summary")] = False,
) -> None:
    """Register SOURCE onto TARGET and print the 4x4 source->target transform.

    Runs in-process on a bundled or --model-dir model, or through a running service with --server.

    Exit codes: 0 done;
    2 bad input (unreadable or invalid cloud, bad option, unknown model, refused by the server);
    1 other failures (model integrity, server unreachable or 5xx).
    """
    from service.pointcloud_io import SUFFIXES, PointCloudFormatError, read_points, write_points

    if write_aligned is not None and write_aligned.suffix.lower() not in SUFFIXES:
        _fail(f"--write-aligned {write_aligned.name}: unknown extension {write_aligned.suffix!r}; expected {SUFFIXES}")
    if server and model_dir:
        _fail("--model-dir only applies in-process; a server uses its own model folders")
    try:
        search = rotation_search_from_options(rotation_search, rotation_search_mode)
    except ValueError as exc:
        _fail(str(exc))
    clouds = []
    for path in (source, target):
        try:
            clouds.append(read_points(path).astype(np.float64))  # [N, 3]
        except PointCloudFormatError as exc:
            _fail(str(exc))
        except OSError as exc:
            _fail(f"cannot read {path}: {exc.strerror or exc}")
    src, tgt = clouds
    init = _read_transform(initial_transform) if initial_transform is not None else None
    refine_mode = refine.value if refine is not None else None if server else SERVICE_DEFAULT_REFINE
    if not server:  # in-process: the service's defaults (with --server the server applies its own)
        search = service_rotation_search(search, refine_mode)
    options = {"iterations": iterations, "keypoints": keypoints, "refine": refine_mode, "initial_transform": init,
               "rotation_search": search, "refine_points": refine_points}
    if not drop_isolated:  # sent only when it departs from the default
        options["drop_isolated"] = False
    if server:
        record = _register_remote(server, api_key, src, tgt, model, options, binary)
    else:
        record = _register_local(src, tgt, model, model_dir or [], threads, options)

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
    typer.echo(json.dumps(record, indent=2) if json_output else _summary(record))


def _read_transform(path: Path) -> list:
    """A 4x4 matrix from ``.json`` (a 4x4 list, or an object with ``transform``) or ``.npy``."""
    try:
        if path.suffix.lower() == ".json":
            payload = json.loads(path.read_text())
            matrix = payload.get("transform") if isinstance(payload, dict) else payload
            if matrix is None:
                _fail(f"--initial-transform {path.name}: JSON object has no 'transform'")
            T = np.asarray(matrix, dtype=np.float64)
        elif path.suffix.lower() == ".npy":
            T = np.load(path, allow_pickle=False).astype(np.float64)
        else:
            _fail(f"--initial-transform {path.name}: expected a .json or .npy file")
    except OSError as exc:
        _fail(f"cannot read {path}: {exc.strerror or exc}")
    except (ValueError, TypeError) as exc:
        _fail(f"--initial-transform {path.name}: not a 4x4 matrix ({exc})")
    if T.shape != (4, 4):
        _fail(f"--initial-transform {path.name}: expected a 4x4 matrix, got shape {list(T.shape)}")
    return T.tolist()


def _register_local(src, tgt, model: str | None, model_dirs: list[Path], threads: int | None, options: dict) -> dict:
    try:
        from service.manifest import ModelIntegrityError
        from service.registrar import InputError, Registrar
    except ImportError as exc:
        _fail(f"{SERVE_EXTRA_HINT} ({exc})")
    directory = _resolve_model_dir(model, model_dirs)
    try:
        registrar = Registrar(directory, threads=threads, warmup=False)
    except ModelIntegrityError as exc:
        _fail(str(exc), code=1)
    except Exception as exc:  # e.g. ONNX Runtime refusing a graph whose hash matches its manifest
        _fail(f"cannot load the model in {directory}: {exc}", code=1)
    try:
        result = registrar.register(src, tgt, **options)
    except InputError as exc:
        _fail(str(exc))
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
    """The folder of ``model`` (a name or a path); without a name: the only model under ``--model-dir``,
    else the bundled ``clean``. Folders under ``--model-dir`` win over bundled ones of the same name."""
    from service.manifest import bundled_models_dir, discover_model_dirs

    if model is not None and Path(model).is_dir():
        return Path(model)
    bundled = discover_model_dirs([])
    extra = [d for d in discover_model_dirs(model_dirs) if d not in bundled]
    candidates = [*extra, *bundled]
    if model is None:
        if len(extra) == 1:
            return extra[0]
        model = DEFAULT_MODEL
    for directory in candidates:
        if directory.name == model:
            return directory
    names = sorted({d.name for d in candidates})
    where = ", ".join(str(d) for d in [bundled_models_dir(), *model_dirs])
    _fail(f"model {model!r} not found in {where}; available: {', '.join(names) or 'none'}")


def _register_remote(server: str, api_key: str | None, src, tgt, model: str | None, options: dict,
                     binary: bool) -> dict:
    try:
        from service.client import MfgnetClient, MfgnetError, pose_from_response
    except ImportError as exc:
        _fail(f"--server needs httpx: {SERVE_EXTRA_HINT} ({exc})")
    try:
        with MfgnetClient(server, api_key=api_key) as client:
            response = client.register(src.astype(np.float32), tgt.astype(np.float32), model=model,
                                       return_correspondences=False, binary=binary, **options)
    except MfgnetError as exc:
        _fail(f"server: {exc}", code=2 if 400 <= exc.status < 500 else 1)
    try:
        R, t = pose_from_response(response)
    except ValueError as exc:
        _fail(f"server: unexpected answer ({exc})", code=1)
    keys = ("quality", "warnings", "model", "iterations", "timing_ms")
    return pose_record(R, t, **{key: response.get(key) for key in keys})


def pose_record(rotation, translation, quality: dict | None, warnings: list | None, model: dict | None,
                iterations: int | None, timing_ms: dict | None) -> dict:
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


def _number(value, spec: str = ".4g") -> str:
    return "?" if value is None else format(float(value), spec)


def _write_text(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        _fail(f"cannot write {path}: {exc.strerror or exc}", code=1)


# ---------------------------------------------------------------------------------------- models


@app.command("models")
def models_command(
    model_dir: ModelDirs = None,
    json_output: Annotated[bool, typer.Option("--json", help="print a JSON list instead of the table")] = False,
) -> None:
    """List the bundled (and --model-dir) models: name, version, iterations, K, accuracy.

    Every model's files are checked against its manifest's sha256;
    models that fail are listed with the reason. Exit code 1 when no usable model is found.
    """
    from service.manifest import ModelIntegrityError, discover_model_dirs, load_manifest

    entries = []
    for directory in discover_model_dirs(model_dir or []):
        try:
            manifest = load_manifest(directory)
        except ModelIntegrityError as exc:
            entries.append({"name": directory.name, "status": "failed", "error": str(exc),
                            "directory": str(directory)})
            continue
        entries.append({
            "name": manifest.name,
            "status": "ok",
            "version": manifest.version,
            "iterations": manifest.config.get("iterations"),
            "keypoints": manifest.config.get("keypoints"),
            "accuracy": manifest.accuracy,
            "sha256": manifest.sha256,
            "directory": str(directory),
        })
    if json_output:
        typer.echo(json.dumps(entries, indent=2))
    else:
        typer.echo(_models_table(entries))
    if not any(entry["status"] == "ok" for entry in entries):
        raise typer.Exit(code=1)


def _models_table(entries: list[dict]) -> str:
    if not entries:
        return "no models found"
    ok = [e for e in entries if e["status"] == "ok"]
    rows = [("NAME", "VERSION", "ITER", "K", "ACCURACY", "DIRECTORY")]
    rows += [(e["name"], e["version"], str(e["iterations"]), str(e["keypoints"]), _accuracy_text(e["accuracy"]),
              e["directory"]) for e in ok]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row[:-1], widths, strict=True)) + "  " + row[-1]
             for row in rows] if ok else []
    lines += [f"FAILED {e['name']}: {e['error']}" for e in entries if e["status"] != "ok"]
    return "\n".join(lines)


def _accuracy_text(accuracy: dict) -> str:
    """``rmse_r 1.2 mae_r 0.6 ... (on X)`` from a manifest's ``accuracy``; ``-`` when there is none."""
    metrics = accuracy.get("metrics", accuracy) if isinstance(accuracy, dict) else {}
    numeric = {k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    keys = [k for k in ACCURACY_KEYS if k in numeric] or list(numeric)[:4]
    if not keys:
        return "-"
    text = " ".join(f"{k} {numeric[k]:.4g}" for k in keys)
    return f"{text} (on {accuracy['on']})" if isinstance(accuracy.get("on"), str) else text


# ------------------------------------------------------------------------------ training plugins


def _missing_command(name: str, error: Exception):
    def command(ctx: typer.Context) -> None:
        typer.echo(f"mfgnet {name}: {TRAIN_EXTRA_HINT} ({error})", err=True)
        raise typer.Exit(code=2)

    command.__doc__ = f"(not installed here: needs the train extra) {name}"  # no [...]: rich markup eats it
    return command


def _register_plugins() -> None:
    torch_missing = find_spec("torch") is None  # checked without importing torch
    for ep in entry_points(group="mfgnet.commands"):
        try:
            if torch_missing:
                raise ImportError("torch is not installed")
            fn = ep.load()
        except ImportError as exc:  # torch or another training dependency is absent
            app.command(ep.name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(
                _missing_command(ep.name, exc))
        else:
            app.command(ep.name)(fn)


_register_plugins()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
