"""Shared by the CLI tests: a verified copy of an exported model, a seeded synthetic pair, and a Python
that cannot see torch.

The model is copied from ``service/models/<name>`` (or from ``$MFGNET_TEST_MODELS/<name>`` when that is
set), so a re-export rewriting the bundled files cannot change it under a running test."""

from __future__ import annotations

import os
import shutil
import sys
import sysconfig
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import smooth_blob

import service
from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest

REPO_ROOT = Path(service.__file__).resolve().parents[1]
TRAINING_ONLY = ("torch", "torchgen", "functorch")  # top-level names of the train extra's torch install


def model_source(name: str = "clean") -> Path:
    root = os.environ.get("MFGNET_TEST_MODELS")
    return (Path(root) if root else bundled_models_dir()) / name


def snapshot_model(dest: Path, name: str = "clean", attempts: int = 5) -> Path:
    """``dest/name``: a copy of the model that passed ``load_manifest``; the test skips when there is none."""
    source = model_source(name)
    for _ in range(attempts):
        shutil.rmtree(dest / name, ignore_errors=True)
        try:
            shutil.copytree(source, dest / name)
            load_manifest(dest / name)
            return dest / name
        except (OSError, ModelIntegrityError):
            time.sleep(2)  # not exported yet, or caught mid-export: try again
    pytest.skip(f"no verified model {name!r} in {source} (not exported yet? set MFGNET_TEST_MODELS)")


def synthetic_pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``source (600, 3)`` and ``target = R source + t`` (float32) with a known small rotation."""
    source = smooth_blob(seed=seed)
    R = Rotation.from_euler("zyx", [12.0, -6.0, 4.0], degrees=True).as_matrix()
    return source, (source @ R.T + np.array([0.05, -0.03, 0.02])).astype(np.float32)


def python_without_torch(workdir: Path) -> tuple[list[str], dict[str, str]]:
    """``(argv prefix, env)`` for a Python that sees this environment's packages except torch, as in the
    container: ``python -S`` (no site-packages) with a folder of links to every package but torch on
    ``PYTHONPATH``, after the repository root. Nothing is patched inside the interpreter."""
    site = Path(sysconfig.get_paths()["purelib"])
    overlay = workdir / "site-packages-without-torch"
    overlay.mkdir(exist_ok=True)
    for entry in site.iterdir():
        top = entry.name.split("-")[0].split(".")[0]
        if top in TRAINING_ONLY or entry.suffix == ".pth" or (overlay / entry.name).exists():
            continue
        (overlay / entry.name).symlink_to(entry)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), str(overlay)])}
    return [sys.executable, "-S"], env
