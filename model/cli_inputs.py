"""The training-side commands' files turned into loaded objects, or a one-line usage error (exit code 2).

Used where the command-line arguments of ``mfgnet train``, ``evaluate``, ``make-pairs``, ``export``,
``import-checkpoint`` and ``bench`` become checkpoints, networks, model folders, pairs and output paths; the messages
and the exit code are the runtime commands' (``service.cli.common.fail``). Only the errors a bad file raises are
caught, here and nowhere deeper.
"""

from __future__ import annotations

import json
import os
import pickle
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer

from model.data import DATA_ENV, UNSEEN_SPLIT_LABEL, NonFiniteShapesError, load_pairs, shapes_file
from service.cli.common import fail

if TYPE_CHECKING:  # torch is imported only by the commands that read checkpoints (make-pairs does not)
    from model.network import MFGNet

# What torch.load(weights_only=True) raises on a file that starts as a checkpoint but is none: a cut-short or foreign
# zip (RuntimeError), a pickle of other bytes (UnpicklingError, or KeyError for an unknown opcode), cut short
# (EOFError).
TORCH_FILE_ERRORS = (pickle.UnpicklingError, EOFError, KeyError, RuntimeError, ValueError)
# What np.load(allow_pickle=False) raises on a file that starts as a zip but is no .npz: a damaged zip (BadZipFile),
# a member that is not an array (ValueError), one cut short (EOFError); and load_pairs' checks (ValueError).
NPZ_FILE_ERRORS = (ValueError, EOFError, zipfile.BadZipFile)


ZIP_MAGIC = b"PK\x03\x04"  # how an .npz (and a PyTorch checkpoint) starts
PICKLE_PROTO = b"\x80"  # how a checkpoint of torch's legacy format (a pickle, protocol 2 or later) starts


def given_options(ctx: typer.Context) -> set[str]:
    """The names of the options the user gave (on the command line, or from their environment variable), not
    defaults (typer's own click: its ParameterSource, by name)."""
    return {name for name in ctx.params
            if getattr(ctx.get_parameter_source(name), "name", None) in ("COMMANDLINE", "ENVIRONMENT", "PROMPT")}


def short(error: BaseException, width: int = 120) -> str:
    """``error``'s first sentence, at most ``width`` characters: a one-line message."""
    text = str(error).strip().splitlines()[0].split(". ")[0] if str(error).strip() else type(error).__name__
    return text if len(text) <= width else text[: width - 3] + "..."


def file_head(path: Path, option: str) -> bytes:
    """The first bytes of the file ``path`` (as many as :data:`ZIP_MAGIC`), or a usage error."""
    try:
        with open(path, "rb") as f:
            return f.read(len(ZIP_MAGIC))
    except OSError as err:
        fail(f"{option} {path}: cannot read ({err.strerror or err})")


def require_zip(path: Path, option: str, what: str) -> None:
    """A usage error unless ``path`` starts as a zip archive (.npz) does: np.load would try it as a pickle."""
    head = file_head(path, option)
    if head != ZIP_MAGIC:
        fail(f"{option} {path}: not {what} ({'empty' if not head else 'not an .npz archive'})")


def input_file(path: Path, option: str) -> Path:
    """``path`` where it is a readable file, else a usage error naming ``option`` and the path."""
    if not path.exists():
        fail(f"{option} {path}: no such file")
    if path.is_dir():
        fail(f"{option} {path}: a folder, not a file")
    if not path.is_file():  # a FIFO or a device: open() could block for ever
        fail(f"{option} {path}: not a regular file")
    if not os.access(path, os.R_OK):
        fail(f"{option} {path}: not readable")
    return path


def output_file(path: Path, option: str, create_folders: bool = False) -> Path:
    """``path`` where a file can be written there (its folder made first with ``create_folders``), else a usage
    error: the path is a folder, or its folder is missing, not a folder or not writable."""
    if path.is_dir():
        fail(f"{option} {path}: a folder, not a file")
    output_folder(path.parent, option, path, create=create_folders)
    return path


def output_folder(folder: Path, option: str, named: Path | None = None, create: bool = True) -> Path:
    """``folder`` where it is (or, with ``create``, can be made) a writable folder, else a usage error naming
    ``option`` and ``named`` (default: the folder)."""
    named = folder if named is None else named
    existing = folder
    while not existing.exists() and existing != existing.parent:  # the nearest folder that is there
        if not create:
            fail(f"{option} {named}: folder {folder} does not exist")
        existing = existing.parent
    if not existing.is_dir():
        fail(f"{option} {named}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        fail(f"{option} {named}: folder {existing} is not writable")
    return folder


def json_file(path: Path, option: str) -> object:
    """The JSON value in the file ``path``, or a usage error."""
    input_file(path, option)
    try:
        return json.loads(path.read_text())
    except OSError as err:
        fail(f"{option} {path}: cannot read ({err.strerror or err})")
    except (ValueError, RecursionError) as err:  # not UTF-8 or not JSON (JSONDecodeError), nested too deeply
        fail(f"{option} {path}: not a JSON file ({short(err)})")


def torch_file(path: Path, option: str) -> object:
    """What ``torch.load(weights_only=True)`` reads from the file ``path``, or a usage error."""
    from model.checkpoint import read_checkpoint

    head = file_head(input_file(path, option), option)
    if not head:
        fail(f"{option} {path}: not a PyTorch checkpoint (empty)")
    if head != ZIP_MAGIC and head[:1] != PICKLE_PROTO:  # text, say: pickle would fail on it in any way
        fail(f"{option} {path}: not a PyTorch checkpoint (neither a zip archive nor a pickle)")
    try:  # not around fail(): its typer.Exit is a RuntimeError
        return read_checkpoint(path)
    except OSError as err:
        fail(f"{option} {path}: cannot read ({err.strerror or err})")
    except EOFError:
        fail(f"{option} {path}: not a PyTorch checkpoint (empty or cut short)")
    except (pickle.UnpicklingError, KeyError):  # torch's messages on these are about weights_only, not the file
        fail(f"{option} {path}: not a PyTorch checkpoint (unreadable data)")
    except TORCH_FILE_ERRORS as err:
        fail(f"{option} {path}: not a PyTorch checkpoint ({short(err)})")


def checkpoint_file(name_or_path: str | Path, option: str = "--checkpoint") -> tuple[Path, dict]:
    """``(path, contents)`` of a checkpoint (a path or a bundled name) holding ``model`` weights and a ``config``,
    or a usage error."""
    from model.checkpoint import resolve_checkpoint

    try:
        path = resolve_checkpoint(name_or_path)
    except FileNotFoundError as err:
        fail(f"{option} {name_or_path}: {err}")
    data = torch_file(path, option)
    if not isinstance(data, dict):
        fail(f"{option} {path}: not a checkpoint (a {type(data).__name__}, not a dict with 'model' and 'config')")
    missing = [key for key in ("model", "config") if not isinstance(data.get(key), dict)]
    if missing and data and all(type(value).__name__ in ("Tensor", "Parameter") for value in data.values()):
        fail(f"{option} {path}: bare weights (a state_dict) without this project's 'model' and 'config'; an authors' "
             f"released checkpoint is converted first: mfgnet import-checkpoint {path} --out CHECKPOINT.pt")
    if missing:
        fail(f"{option} {path}: not a checkpoint of this project (no {' or '.join(map(repr, missing))} dict)")
    return path, data


def load_weights(model: MFGNet, weights: dict, path: Path, option: str) -> MFGNet:
    """``model`` with ``weights`` loaded, or a usage error saying which keys or shapes do not fit."""
    from model.checkpoint import weights_mismatch

    mismatch = weights_mismatch(model, weights)
    if mismatch:
        fail(f"{option} {path}: the weights do not fit the network: {mismatch}")
    model.load_state_dict(weights)
    return model


def checkpoint_model(name_or_path: str | Path, option: str = "--checkpoint") -> tuple[Path, dict, MFGNet]:
    """``(path, contents, network in eval mode)`` of a checkpoint whose weights fit its config, or a usage error."""
    from model.config import MFGNetConfig
    from model.network import MFGNet

    path, data = checkpoint_file(name_or_path, option)
    try:
        model = MFGNet(MFGNetConfig.from_dict(data["config"]))
    except (TypeError, ValueError) as err:  # a config value of the wrong type
        fail(f"{option} {path}: invalid config ({short(err)})")
    return path, data, load_weights(model, data["model"], path, option).eval()


def model_dir(model: str | Path, option: str = "--model") -> Path:
    """The folder of an ONNX model (a model folder, or the name of a bundled model) whose manifest and graphs check
    out, else a usage error naming ``option`` and what was given."""
    from service.manifest import ModelIntegrityError, discover_model_dirs, load_manifest, model_folder

    folder = model_folder(model)
    if not str(model) or not folder.exists():  # "" would name the folder of bundled models
        bundled = ", ".join(path.name for path in discover_model_dirs([])) or "none"
        fail(f"{option} {model}: no such model folder, nor a bundled model (bundled: {bundled})")
    if not folder.is_dir():
        fail(f"{option} {model}: a file, not a model folder")
    try:
        load_manifest(folder)
    except ModelIntegrityError as err:
        fail(f"{option} {model}: not a usable model folder ({err})")
    except OSError as err:
        fail(f"{option} {model}: cannot read ({err.strerror or err})")
    return folder


def pairs_file(path: Path, option: str = "--pairs") -> dict[str, np.ndarray]:
    """The pairs of a ``mfgnet make-pairs`` file, or a usage error."""
    require_zip(input_file(path, option), option, "a pairs file")
    try:
        return load_pairs(path)
    except OSError as err:
        fail(f"{option} {path}: cannot read ({err.strerror or err})")
    except zipfile.BadZipFile as err:
        fail(f"{option} {path}: not a pairs file (a damaged .npz: {short(err)})")
    except NPZ_FILE_ERRORS as err:  # load_pairs' checks name the file
        fail(f"{option}: {short(err, 200)}")


def require_shapes(split: str, setting: str, data: str | None, hint: str = f"set --data or ${DATA_ENV}") -> Path:
    """The ModelNet40 file of ``split`` and ``setting`` under ``--data`` / ``$MFGNET_DATA``, checked to be an
    ``.npz`` with ``points`` and ``labels``; else a usage error, ``hint`` saying where the folder is set (a command
    without ``--data``: ``"set $MFGNET_DATA"``)."""
    try:
        file = shapes_file(split, setting, data)
    except ValueError as err:  # an unknown split or setting
        fail(str(err))
    if not file.parent.is_dir():
        fail(f"ModelNet40 folder not found: {file.parent} ({hint})")
    if not file.is_file():
        fail(f"ModelNet40 file not found: {file} ({hint})")
    require_zip(file, "ModelNet40 file", "a ModelNet40 .npz")
    try:
        archive = np.load(file, allow_pickle=False)
    except OSError as err:
        fail(f"ModelNet40 file {file}: cannot read ({err.strerror or err})")
    except NPZ_FILE_ERRORS as err:
        fail(f"ModelNet40 file {file}: not a ModelNet40 .npz ({short(err)})")
    if not isinstance(archive, np.lib.npyio.NpzFile):
        fail(f"ModelNet40 file {file}: one array, not an .npz of 'points' and 'labels'")
    with archive:
        missing = [key for key in ("points", "labels") if key not in archive.files]
        if missing:
            fail(f"ModelNet40 file {file}: not a ModelNet40 .npz (no {' or '.join(map(repr, missing))})")
        if setting == "unseen":  # its category split: labels below UNSEEN_SPLIT_LABEL train, the others test
            labels = np.asarray(archive["labels"])
            chosen = labels < UNSEEN_SPLIT_LABEL if split == "train" else labels >= UNSEEN_SPLIT_LABEL
            if not chosen.any():
                held = f"labels {labels.min()}-{labels.max()}" if len(labels) else "no shapes"
                fail(f"ModelNet40 file {file}: no shapes for setting 'unseen', whose {split} split is the labels "
                     f"{'below' if split == 'train' else 'from'} {UNSEEN_SPLIT_LABEL} (it holds {held}); the unseen "
                     f"setting needs more than {UNSEEN_SPLIT_LABEL} classes")
    return file


@contextmanager
def finite_shapes() -> Iterator[None]:
    """Runs the body that loads ModelNet40 shapes (:func:`model.data.load_shapes`): a file holding a shape with NaN or
    infinite coordinates is a usage error naming the file and the shapes' indices, before any pair is made or any
    batch trained (the shapes are checked as they are loaded, not read twice)."""
    try:
        yield
    except NonFiniteShapesError as err:
        fail(str(err))
