"""Training-side ``mfgnet export`` and ``mfgnet import-checkpoint`` (entry-point plugins)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Annotated

import typer


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
    from model.checkpoint import load_model, read_checkpoint, resolve_checkpoint
    from model.data import make_test_pairs
    from service.registrar import Registrar

    path = resolve_checkpoint(checkpoint)
    model = load_model(path)
    data = read_checkpoint(path)
    accuracy = json.loads(accuracy_json.read_text()) if accuracy_json else {}
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
    from export.official import import_official
    from model.checkpoint import save_checkpoint

    model = import_official(source)
    save_checkpoint(out, model, source=source.name, imported="authors' released checkpoint (MIT)")
    typer.echo(f"imported {source.name} -> {out} ({model.cfg.iterations} iterations, K = {model.cfg.keypoints})")
