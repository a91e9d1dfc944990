"""A doc command that re-exports a bundled model (``mfgnet export ... --out service/models/NAME``) writes what the
bundled folder holds: NAME's checkpoint, its manifest's version and the setting the checkpoint was trained on. Nothing
is exported: the command's options are parsed by its click command."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import torch
import typer

from service.cli import app

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RE_EXPORT = re.compile(r"mfgnet export ([^`#\n]*--out service/models/([a-z0-9_.-]+)[^`#\n]*)")


def export_params(args: str) -> dict:
    """The options of ``mfgnet export ARGS`` as the command receives them (defaults filled in)."""
    group = typer.main.get_command(app)
    parent = group.make_context("mfgnet", [], resilient_parsing=True)
    return group.get_command(parent, "export").make_context("export", shlex.split(args), parent=parent).params


def test_a_doc_command_that_re_exports_a_bundled_model_reproduces_its_manifest() -> None:
    found = [(doc.name, *match.groups()) for doc in DOCS for match in RE_EXPORT.finditer(doc.read_text())]
    assert found, "no doc shows re-exporting a bundled model"
    for doc, args, name in found:
        params = export_params(args)
        manifest = json.loads((ROOT / "service" / "models" / name / "manifest.json").read_text())
        checkpoint = torch.load(ROOT / "model" / "checkpoints" / f"{name}.pt", weights_only=True)
        assert params["checkpoint"] == name, (doc, args)
        assert params["version"] == manifest["version"], (doc, args, "the bundled version")
        assert (params["setting"] or checkpoint["setting"]) == checkpoint["setting"], (doc, args)
