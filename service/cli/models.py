"""``mfgnet models``: the bundled and ``--model-dir`` models, each checked against its manifest, as a table or JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from service.cli.model_lookup import default_model_dir
from service.cli.options import ModelDirs

if TYPE_CHECKING:
    from service.manifest import Manifest

# What each bundled model is for, shown by `mfgnet models` (a manifest's own "description" wins). The table shows
# no accuracy figures: each manifest's are on that model's own validation pairs, not comparable across models.
MODEL_PURPOSES = {
    "general": "independently sampled scans",
    "clean": "paper protocol: shared points, clean",
    "noise": "paper protocol: shared points, noisy",
    "unseen": "paper protocol: categories 0-19 only",
}
MODELS_TABLE_WIDTH = 100


def models_command(
    model_dir: ModelDirs = None,
    json_output: Annotated[bool, typer.Option("--json", help="print a JSON list instead of the table")] = False,
) -> None:
    """List the bundled (and --model-dir) models: name, version, what each is for; * marks the default.

    Every model's files are checked against its manifest's sha256;
    models that fail are listed with the reason. Exit code 1 when no usable model is found.
    """
    from service.manifest import discover_model_dirs

    default = default_model_dir(model_dir or [])
    entries = [_model_entry(directory, directory == default) for directory in discover_model_dirs(model_dir or [])]
    if json_output:
        typer.echo(json.dumps(entries, indent=2))
    else:
        typer.echo(_models_table(entries))
    if not any(entry["status"] == "ok" for entry in entries):
        raise typer.Exit(code=1)


def _bundled_purpose(manifest: Manifest) -> str | None:
    """``MODEL_PURPOSES``' line for a bundled model, or for a copy of it (the same manifest); ``None`` for any other
    model, also one that shares a bundled model's name (a fine-tune exported as ``general``)."""
    from service.manifest import bundled_models_dir, sha256_file

    bundled = bundled_models_dir() / manifest.name / "manifest.json"
    if manifest.name not in MODEL_PURPOSES or not bundled.is_file() or sha256_file(bundled) != manifest.sha256:
        return None
    return MODEL_PURPOSES[manifest.name]


def _model_entry(directory: Path, default: bool) -> dict:
    """One model folder as ``mfgnet models --json`` lists it (``status`` ``ok`` or ``failed`` with ``error``)."""
    from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest

    try:
        manifest = load_manifest(directory)
    except ModelIntegrityError as exc:
        return {"name": directory.name, "status": "failed", "default": default, "error": str(exc),
                "directory": str(directory)}
    description = manifest.raw.get("description")
    return {
        "name": manifest.name,
        "status": "ok",
        "default": default,
        "version": manifest.version,
        "purpose": description if isinstance(description, str) else _bundled_purpose(manifest),
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
    rows += [
        (
            "*" if e["default"] else "",
            e["name"],
            e["version"],
            str(e["iterations"]),
            str(e["keypoints"]),
            f"{e['size_bytes'] / 2**20:.1f} MiB",
            e["purpose"] or "-",
            "bundled" if e["bundled"] else e["directory"],
        )
        for e in ok
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]) - 1)]
    room = MODELS_TABLE_WIDTH - sum(widths) - 2 * (len(widths) - 1) - 1
    lines = [_models_row(row, widths, room) for row in rows] if ok else []
    if any(e["default"] for e in ok):
        lines.append("* the default: what `mfgnet register` runs without --model (a server: MFGNET_DEFAULT_MODEL)")
    lines += [_elide(f"FAILED {e['name']}: {e['error']}", MODELS_TABLE_WIDTH) for e in entries if e["status"] != "ok"]
    lines += [f"the default, {e['name']}, failed: `mfgnet register` without --model stops on it" for e in entries
              if e["status"] != "ok" and e["default"]]
    return "\n".join(lines)


def _models_row(row: tuple[str, ...], widths: list[int], room: int) -> str:
    cells = [cell.ljust(width) for cell, width in zip(row[:-1], widths, strict=True)]
    return (cells[0] + " " + "  ".join(cells[1:]) + "  " + _elide(row[-1], room, left=True)).rstrip()


def _elide(text: str, width: int, left: bool = False) -> str:
    """``text`` cut to ``width`` characters with ``...`` (at the start when ``left``: a path's tail names it)."""
    if len(text) <= width:
        return text
    return "..." + text[len(text) - width + 3 :] if left else text[: width - 3] + "..."
