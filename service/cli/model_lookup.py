"""Which model folder a command runs (a bundled model's name, one under ``--model-dir``, or a folder), and loading it
in process."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from service.cli.common import SERVE_EXTRA_HINT, fail
from service.request_defaults import DEFAULT_MODEL

if TYPE_CHECKING:  # onnxruntime loads only in the commands that register
    from service.in_process import LocalRegistrar


def load_registrar(model: str | None, model_dirs: list[Path], threads: int | None) -> LocalRegistrar:
    """The :class:`service.in_process.LocalRegistrar` of ``model`` (see :func:`resolve_model_dir`), not warmed up;
    exit 1 when its files fail their check or ONNX Runtime refuses them."""
    try:
        from service.in_process import LocalRegistrar
        from service.manifest import ModelIntegrityError
    except ImportError as exc:
        fail(f"{SERVE_EXTRA_HINT} ({exc})")
    directory = resolve_model_dir(model, model_dirs)
    try:
        return LocalRegistrar(directory, threads=threads, warmup=False)
    except ModelIntegrityError as exc:
        fail(str(exc), code=1)
    except Exception as exc:  # e.g. ONNX Runtime refusing a graph whose hash matches its manifest
        fail(f"cannot load the model in {directory}: {exc}", code=1)


def resolve_model_dir(model: str | None, model_dirs: list[Path]) -> Path:
    """The folder of ``model`` (a model's name, else a path); without a name: :func:`default_model_dir`.
    Folders under ``--model-dir`` win over bundled ones of the same name; a name wins over a folder of that name in
    the working directory (a training run's ``--out runs/general`` beside it), unless written as a path (``./x``)."""
    from service.manifest import bundled_models_dir

    extra, bundled = extra_and_bundled_dirs(model_dirs)
    if model is None and len(extra) == 1:
        return extra[0]
    name = DEFAULT_MODEL if model is None else model
    for directory in [*extra, *bundled]:
        if directory.name == name:
            return directory
    if model and Path(model).is_dir():  # "" would name the working directory
        return Path(model)
    names = sorted({d.name for d in [*extra, *bundled]})
    where = ", ".join(str(d) for d in [bundled_models_dir(), *model_dirs])
    fail(f"model {name!r} not found in {where}; available: {', '.join(names) or 'none'}")


def extra_and_bundled_dirs(model_dirs: list[Path]) -> tuple[list[Path], list[Path]]:
    """``(the model folders under --model-dir that are not bundled, the bundled ones)``; a usage error where a
    ``--model-dir`` is not a folder or holds no model (it was ignored)."""
    from service.manifest import discover_model_dirs

    missing = [str(d) for d in model_dirs if not d.is_dir()]
    if missing:
        fail(f"--model-dir {missing[0]}: not a folder")
    empty = [str(d) for d in model_dirs if holds_no_model(d)]
    if empty:  # as `mfgnet serve` refuses it: the bundled models ran instead, without a word
        fail(f"--model-dir {empty[0]}: no model in it (a manifest.json or .onnx files, in it or in its subfolders)")
    bundled = discover_model_dirs([])
    return [d for d in discover_model_dirs(model_dirs) if d not in bundled], bundled


def holds_no_model(folder: Path) -> bool:
    """Whether the model folder ``folder`` holds no model, in it or in a subfolder (an empty or mis-mounted volume);
    ``False`` where it cannot be read, which the model registry names."""
    from service.manifest import models_in

    try:
        return not models_in(folder)
    except OSError:
        return False


def default_model_dir(model_dirs: list[Path]) -> Path | None:
    """What ``mfgnet register`` runs without ``--model``: the only model under ``--model-dir``, else the first
    folder named ``DEFAULT_MODEL`` (``--model-dir`` ones first); ``None`` when there is none."""
    extra, bundled = extra_and_bundled_dirs(model_dirs)
    if len(extra) == 1:
        return extra[0]
    return next((d for d in [*extra, *bundled] if d.name == DEFAULT_MODEL), None)
