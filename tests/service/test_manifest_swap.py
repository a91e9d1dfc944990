"""A graph file swapped after its manifest was verified is never served: the runtime builds each session from the
bytes it hashes (``Manifest.graph_bytes``), not from the path a second time."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest
from service.registrar import Registrar


def test_a_graph_swapped_after_verification_is_refused(tmp_path: Path) -> None:
    model = shutil.copytree(bundled_models_dir() / "general", tmp_path / "general")
    manifest = load_manifest(model)  # every graph verified here
    shutil.copyfile(bundled_models_dir() / "clean" / "encoder.onnx", model / "encoder.onnx")  # a valid graph
    with pytest.raises(ModelIntegrityError, match=r"encoder\.onnx does not match"):
        manifest.graph_bytes("encoder")


def test_the_registrar_builds_its_sessions_from_verified_bytes(tmp_path: Path) -> None:
    model = shutil.copytree(bundled_models_dir() / "general", tmp_path / "general")
    Registrar(model, threads=1)  # the untouched copy loads
    shutil.copyfile(bundled_models_dir() / "clean" / "encoder.onnx", model / "encoder.onnx")
    with pytest.raises(ModelIntegrityError, match=r"encoder\.onnx"):
        Registrar(model, threads=1)
