"""Training-side ``mfgnet export`` and ``mfgnet import-checkpoint`` (entry-point plugins)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Annotated

import typer

from model.cli_inputs import fail, short


def export(
    checkpoint: Annotated[str, typer.Option(help="checkpoint path or bundled name (clean, noise, ...)")],
    out: Annotated[Path, typer.Option(help="model directory; its folder name is the model name")],
    version: Annotated[str, typer.Option(help="model version written to the manifest")] = "0.1.0",
    setting: Annotated[str, typer.Option(help="setting of the parity pairs and reference radius")] = "clean",
    parity_pairs: Annotated[int, typer.Option(help="seeded pairs for the parity check (>= 50)")] = 100,
    parity_setting: Annotated[
        str,
        typer.Option(help="pairs for parity; 'noise' by default: in clean pairs source and target share exact "
                          "points, and once aligned the unit-difference feature at ~0 distance turns float32 vs "
                          "float64 rounding of the pose into different matches (docs/DESIGN.md)"),
    ] = "noise",
    accuracy_json: Annotated[Path | None, typer.Option(help="metrics JSON (mfgnet evaluate --json)")] = None,
    seed: int = 0,
) -> None:
    """Export a checkpoint to ONNX (encoder + matcher graphs) with a manifest; fails on parity."""
    from export.onnx_export import write_model_folder
    from export.parity import ParityError, check_parity
    from model.cli_inputs import checkpoint_model, json_file, output_folder, require_shapes
    from model.data import make_test_pairs
    from service.registrar import Registrar

    if out.exists() and not out.is_dir():
        fail(f"--out {out}: a file, not a model folder")
    output_folder(out, "--out")
    path, data, model = checkpoint_model(checkpoint)
    accuracy = json_file(accuracy_json, "--accuracy-json") if accuracy_json else {}
    require_shapes("test", parity_setting, None)  # the parity pairs' shapes
    if not accuracy and "val" in data:
        accuracy = {"metrics": data["val"], "on": "validation pairs held out of the training split"}
    if accuracy_json:
        accuracy = {"metrics": accuracy, "on": str(accuracy_json.name)}
    out.mkdir(parents=True, exist_ok=True)
    write_model_folder(out, path, model, data, setting, version, accuracy)
    registrar = Registrar(out, warmup=False)
    pairs = make_test_pairs(parity_setting, "test", count=parity_pairs, seed=seed)
    try:
        report = check_parity(model, registrar, pairs, min_compared=min(50, parity_pairs))
    except ParityError as exc:
        shutil.rmtree(out)
        typer.echo(f"export failed, {out} removed: {exc}", err=True)
        raise typer.Exit(code=1) from None
    manifest_path = out / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["parity"] = {**report.to_dict(), "setting": parity_setting, "seed": seed}
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    typer.echo(json.dumps(manifest["parity"], indent=2))
    typer.echo(f"exported {out.name} to {out}")


def import_checkpoint(
    source: Annotated[Path, typer.Argument(help="the authors' model_*.t7")],
    out: Annotated[Path, typer.Option(help="project checkpoint to write (.pt); never commit it")],
) -> None:
    """Import an authors' released checkpoint (215 keys) into this project's checkpoint format."""
    import torch

    from export.official import OFFICIAL_CONFIG, convert_state_dict
    from model.checkpoint import save_checkpoint
    from model.cli_inputs import load_weights, output_file, torch_file
    from model.network import MFGNet

    output_file(out, "--out", create_folders=True)
    official = torch_file(source, "SOURCE")
    if not isinstance(official, dict) or not all(isinstance(value, torch.Tensor) for value in official.values()):
        fail(f"SOURCE {source}: not an authors' released checkpoint (not a dict of tensors)")
    try:
        weights = convert_state_dict(official)
    except (ValueError, KeyError) as err:  # the wrong number of tensors, an unknown key, no head.reflect
        fail(f"SOURCE {source}: not an authors' released checkpoint ({short(err)})")
    model = load_weights(MFGNet(OFFICIAL_CONFIG), weights, source, "SOURCE").eval()
    save_checkpoint(out, model, source=source.name, imported="authors' released checkpoint (MIT)")
    typer.echo(f"imported {source.name} -> {out} ({model.cfg.iterations} iterations, K = {model.cfg.keypoints})")
