"""Training-side ``mfgnet export`` and ``mfgnet import-checkpoint`` (entry-point plugins)."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Annotated

import typer

from export import MIN_COMPARED
from model.cli_inputs import fail, finite_shapes, require_shapes, short
from service.manifest import MANIFEST, ModelIntegrityError, looks_like_model

STAGING_PREFIX = ".export-"  # the hidden folder a model is written and checked in before it is moved to --out
MODEL_VERSION = re.compile(r"[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}")  # a manifest's version: one table cell, no space
DESCRIPTION_CHARS = 60  # longest manifest description: one cell of the 100-column `mfgnet models` table


def export(
    checkpoint: Annotated[str, typer.Option(help="checkpoint path or bundled name (clean, noise, ...)")],
    out: Annotated[Path, typer.Option(help="model directory (new, empty, or a model folder to re-export); its folder "
                                           "name is the model name")],
    version: Annotated[str, typer.Option(help="model version written to the manifest")] = "0.1.0",
    setting: Annotated[
        str | None,
        typer.Option(help="setting whose training shapes give the reference radius the runtime scales clouds to "
                          "(one of clean, noise, unseen, resampled) [default: the setting the checkpoint was trained "
                          "on, else clean]"),
    ] = None,
    parity_pairs: Annotated[
        int, typer.Option(min=1, help="seeded pairs for the parity check; the graphs are compared on all of them, the "
                                      "final poses on the comparable ones (pairs near a tie are excluded: about half "
                                      "of them for the bundled clean)")
    ] = 100,
    min_comparable: Annotated[
        int, typer.Option(min=1, help="comparable pairs (not excluded as ties) parity needs; at most --parity-pairs")
    ] = MIN_COMPARED,
    parity_setting: Annotated[
        str,
        typer.Option(help="pairs for parity; 'noise' by default: in clean pairs source and target share exact "
                          "points, and once aligned the unit-difference feature at ~0 distance turns float32 vs "
                          "float64 rounding of the pose into different matches (docs/DESIGN.md)"),
    ] = "noise",
    accuracy_json: Annotated[Path | None, typer.Option(help="metrics JSON (mfgnet evaluate --json)")] = None,
    seed: int = 0,
    shapes_folder: Annotated[
        str | None, typer.Option("--data", help="ModelNet40 directory: the reference radius' training shapes and the "
                                                "parity pairs' test shapes ($MFGNET_DATA)")
    ] = None,
    description: Annotated[
        str | None,
        typer.Option(help=f"what the model is for, one line of at most {DESCRIPTION_CHARS} characters: the FOR column "
                          "of `mfgnet models` [default: a re-exported folder's own, else none]"),
    ] = None,
) -> None:
    """Export a checkpoint to ONNX (encoder + matcher graphs) with a manifest; fails on parity.

    The model is written and checked in a staging folder and moved into OUT only once parity passed: a failed or
    interrupted export leaves OUT as it was. Re-exporting into a model folder replaces its graphs and manifest and
    keeps every other file there.
    """
    from export.onnx_export import write_model_folder
    from export.parity import ParityError, check_parity
    from model.cli_inputs import checkpoint_model, json_file
    from model.data import make_test_pairs
    from service.registrar import Registrar

    if not MODEL_VERSION.fullmatch(version):  # written to the manifest, shown in `mfgnet models` and /v1/models
        fail(f"--version {version!r}: up to 64 letters, digits, '.', '+', '_' or '-', starting with a letter or digit "
             "(e.g. 1.2.0)")
    if min_comparable > parity_pairs:
        fail(f"--min-comparable {min_comparable}: more than the {parity_pairs} --parity-pairs (about half the pairs "
             "can be excluded as ties: give at least twice as many pairs)")
    check_model_out(out)
    description = model_description(description, out)
    path, data, model = checkpoint_model(checkpoint)
    setting = radius_setting(setting, data, path, shapes_folder)
    accuracy = json_file(accuracy_json, "--accuracy-json") if accuracy_json else {}
    require_shapes("test", parity_setting, shapes_folder)  # the parity pairs' shapes
    if not accuracy and "val" in data:
        accuracy = {"metrics": data["val"], "on": "validation pairs held out of the training split"}
    if accuracy_json:
        accuracy = accuracy_section(accuracy, accuracy_json, path)
    with staged_model_folder(out) as stage:
        with finite_shapes():  # the reference radius' training shapes, the parity pairs' test shapes
            write_model_folder(stage, path, model, data, setting, version, accuracy, shapes_folder)
            pairs = make_test_pairs(parity_setting, "test", count=parity_pairs, seed=seed, path=shapes_folder)
            if len(pairs["source"]) < parity_pairs:  # one pair per test shape at most
                typer.echo(f"note: the test split holds {len(pairs['source'])} shapes: parity on as many pairs, not "
                           f"--parity-pairs {parity_pairs}", err=True)
        try:
            registrar = Registrar(stage, warmup=False)
        except ModelIntegrityError as exc:  # a config the runtime refuses
            fail(f"export failed, {out} left as it was: {exc}", code=1)
        try:
            report = check_parity(model, registrar, pairs, min_compared=min_comparable)
        except ParityError as exc:
            advice = untrained_advice(checkpoint, data) if exc.nearly_identical_embeddings else ""
            fail(f"export failed, {out} left as it was: {exc}{advice}", code=1)
        manifest_path = stage / MANIFEST
        manifest = json.loads(manifest_path.read_text())
        manifest["parity"] = {**report.to_dict(), "setting": parity_setting, "seed": seed}
        if description:
            manifest["description"] = description
        manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
        stale = install_model_folder(stage, out)
    typer.echo(json.dumps(manifest["parity"], indent=2))
    if stale:
        typer.echo(f"note: {out} still holds graphs of the previous export that its manifest no longer names: "
                   f"{', '.join(stale)}", err=True)
    typer.echo(f"exported {out.name} to {out}")


def untrained_advice(checkpoint: str, data: dict) -> str:
    """What to do about a parity failure of an untrained network (``data``: the checkpoint's contents, whose
    training amount is quoted where it records one). Parity stays as it is: there is no export without it."""
    state, val = data.get("state"), data.get("val")
    recorded = []
    if isinstance(state, dict) and isinstance(state.get("epoch"), int):
        recorded.append(f"{state['epoch']} epoch{'s' if state['epoch'] != 1 else ''}")
    if isinstance(val, dict) and isinstance(val.get("mae_r"), int | float):
        recorded.append(f"validation MAE(R) {val['mae_r']:.1f} deg")
    trained = f" (this checkpoint records {', '.join(recorded)})" if recorded else ""
    return (f". What to do: train longer{trained}; a smoke run of a few batches only checks the set-up. The bundled "
            f"checkpoints (clean, noise, unseen, general) export cleanly; `mfgnet evaluate --checkpoint {checkpoint}` "
            "measures this one in PyTorch without an export")


def model_description(description: str | None, out: Path) -> str | None:
    """The manifest's ``description``: ``description`` where given (a usage error unless it is one line of at most
    :data:`DESCRIPTION_CHARS` printable characters), else the one of the model folder ``out`` re-exports, if any."""
    if description is None:
        previous = previous_manifest(out).get("description")
        return previous if isinstance(previous, str) else None
    if not description.strip() or not description.isprintable() or len(description) > DESCRIPTION_CHARS:
        fail(f"--description {description!r}: give one line of 1 to {DESCRIPTION_CHARS} printable characters "
             f"(got {len(description)})")
    return description.strip()


def radius_setting(setting: str | None, checkpoint: dict, path: Path, shapes_folder: str | None = None) -> str:
    """The setting whose training shapes give the reference radius: ``setting`` where given, else the one the
    checkpoint was trained on (``clean`` where it records none); a usage error unless it is a setting with a training
    split whose ModelNet40 file is there (in ``shapes_folder``, else :func:`model.data.data_dir`'s)."""
    from model.data import DENSE_SETTINGS, SETTINGS

    trainable = [name for name in SETTINGS if name not in DENSE_SETTINGS]
    if setting is None:
        trained = checkpoint.get("setting")
        setting = trained if isinstance(trained, str) else "clean"
        if setting not in trainable:
            fail(f"--checkpoint {path}: trained on setting {setting!r}, which has no training shapes to measure the "
                 f"reference radius on; give --setting (one of {', '.join(trainable)})")
    elif setting not in trainable:
        what = "a test-only setting" if setting in SETTINGS else "unknown setting"
        fail(f"--setting {setting}: {what}; the reference radius is measured on a setting's training shapes (one of "
             f"{', '.join(trainable)})")
    require_shapes("train", setting, shapes_folder)
    return setting


def accuracy_section(metrics: object, accuracy_json: Path, checkpoint: Path) -> dict:
    """The manifest's ``accuracy`` from ``mfgnet evaluate --json`` output: the metrics, the file's name, and what
    they were measured on and with (``evaluated``: the pairs, the checkpoint or model, the runtime options), which
    evaluate writes since it records them; a usage error where that was another checkpoint than the one exported."""
    from model.checkpoint import file_sha256

    evaluated = metrics.pop("evaluated", None) if isinstance(metrics, dict) else None
    if not isinstance(evaluated, dict):  # written before evaluate recorded it
        return {"metrics": metrics, "on": str(accuracy_json.name)}
    measured = evaluated.get("checkpoint_sha256")
    if measured != file_sha256(checkpoint):
        what = (f"baseline {evaluated['baseline']}" if evaluated.get("baseline")
                else f"another checkpoint (sha256 {measured[:12]}...)" if isinstance(measured, str)
                else "a model that does not record its checkpoint")
        fail(f"--accuracy-json {accuracy_json}: measured with {what}, not with --checkpoint {checkpoint}")
    return {"metrics": metrics, "on": str(accuracy_json.name), "evaluated": evaluated}


def check_model_out(out: Path) -> None:
    """A usage error unless ``out`` is where a model can be exported: a new or empty folder, or a model folder (a
    manifest or ONNX graphs) to re-export, in a writable place, named as a model."""
    from model.cli_inputs import output_folder
    from service.manifest import MODEL_NAME

    if out.exists() and not out.is_dir():
        fail(f"--out {out}: a file, not a model folder")
    if not MODEL_NAME.match(out.name):
        fail(f"--out {out}: {out.name!r} is no model name (the folder's name: up to 64 lowercase letters, digits, "
             "'_', '.', '-')")
    output_folder(out, "--out")
    others = out.is_dir() and any(not path.name.startswith(STAGING_PREFIX) for path in out.iterdir())
    if others and not looks_like_model(out):  # a staging folder left by a killed export is no reason to refuse
        fail(f"--out {out}: a folder of other files, not a model folder (name a new or empty folder, or a model "
             "folder to re-export)")


@contextmanager
def staged_model_folder(out: Path) -> Iterator[Path]:
    """A fresh, empty folder named as ``out`` to write the model into, on ``out``'s file system: inside ``out``
    when it exists (a hidden folder), else beside it. It and everything in it is removed on leaving; so are the
    folders above ``out`` that were made for it, should the model not be installed."""
    made = [folder for folder in out.parents if not folder.exists()][::-1]  # the outermost first
    for folder in made:
        folder.mkdir()
    root = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX if out.is_dir() else f".{out.name}{STAGING_PREFIX}",
                                 dir=out if out.is_dir() else out.parent))
    try:
        stage = root / out.name
        stage.mkdir()
        yield stage
    finally:
        shutil.rmtree(root, ignore_errors=True)  # made above: holds only what this export wrote
        if not out.exists():
            for folder in reversed(made):
                with suppress(OSError):  # only while empty
                    folder.rmdir()


def install_model_folder(stage: Path, out: Path) -> list[str]:
    """Move the checked model in ``stage`` to ``out``; returns the graph files of a previous export that ``out``
    still holds and the new manifest does not name.

    A missing ``out`` becomes ``stage`` in one rename. Into an existing folder each file is replaced in one rename
    (the manifest last, so that it never names a graph not yet there); the folder's other files stay."""
    if not out.exists():
        os.rename(stage, out)
        return []
    files = sorted((path.name for path in stage.iterdir()), key=lambda name: name == MANIFEST)  # manifest last
    blocked = [name for name in files if (out / name).is_dir() or (out / name).is_symlink()]
    if blocked:
        fail(f"--out {out}: {blocked[0]} there is a folder or a link; nothing was replaced", code=1)
    old_graphs = previous_graph_files(out)
    for name in files:
        os.replace(stage / name, out / name)
    return sorted(name for name in old_graphs - set(files) if (out / name).is_file())


def previous_manifest(folder: Path) -> dict:
    """The manifest in ``folder`` (empty where it is missing, unreadable or not a JSON object)."""
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError):
        return {}
    return manifest if isinstance(manifest, dict) else {}


def previous_graph_files(folder: Path) -> set[str]:
    """The graph files the manifest in ``folder`` names (none where it is missing or unreadable)."""
    try:
        return {Path(entry["file"]).name for entry in previous_manifest(folder)["graphs"].values()}
    except (KeyError, TypeError, AttributeError):
        return set()


def import_checkpoint(
    source: Annotated[Path, typer.Argument(help="the authors' model_*.t7")],
    out: Annotated[Path, typer.Option(help="project checkpoint to write (.pt); never commit it")],
) -> None:
    """Import an authors' released checkpoint (215 keys) into this project's checkpoint format."""
    import torch

    from export.official import convert_state_dict
    from model.checkpoint import save_checkpoint
    from model.cli_inputs import load_weights, output_file, torch_file
    from model.config import OFFICIAL_CONFIG
    from model.network import MFGNet

    if out.exists() and not out.is_dir():  # a checkpoint (a training run's) is not replaced without a word
        fail(f"--out {out}: already exists; remove it or name another file")
    output_file(out, "--out", create_folders=True)
    official = torch_file(source, "SOURCE")
    if isinstance(official, dict) and all(isinstance(official.get(key), dict) for key in ("model", "config")):
        fail(f"SOURCE {source}: already a checkpoint of this project (its 'model' weights and 'config'), usable "
             "directly with --checkpoint; nothing to import")
    if not isinstance(official, dict) or not all(isinstance(value, torch.Tensor) for value in official.values()):
        fail(f"SOURCE {source}: not an authors' released checkpoint (not a dict of tensors)")
    try:
        weights = convert_state_dict(official)
    except (ValueError, KeyError) as err:  # the wrong number of tensors, an unknown key, no head.reflect
        fail(f"SOURCE {source}: not an authors' released checkpoint ({short(err)})")
    model = load_weights(MFGNet(OFFICIAL_CONFIG), weights, source, "SOURCE").eval()
    save_checkpoint(out, model, source=source.name, imported="authors' released checkpoint (MIT)")
    typer.echo(f"imported {source.name} -> {out} ({model.cfg.iterations} iterations, K = {model.cfg.keypoints})")
