"""Runs of the aligned-download tests: ``mfgnet register`` and ``sequence`` with ``--write-aligned`` and one small
matcher pass (the tests check the files written, not accuracy), the pose a run wrote, and the page's
``POST /v1/register/aligned``; the model to register with is ``tests/service/conftest.py``'s ``model_dir``."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
from click.testing import Result
from typer.testing import CliRunner

from service.cli import app

runner = CliRunner()
FAST = ("--iterations", "1", "--keypoints", "32")


def register(*args: object, model_dir: Path) -> Result:
    """``mfgnet register ARGS --model-dir MODEL_DIR`` with the ``FAST`` options."""
    return runner.invoke(app, ["register", *map(str, args), "--model-dir", str(model_dir), *FAST])


def sequence(frames: list[Path], folder: Path, model_dir: Path, steps: Path | None = None) -> Result:
    """``mfgnet sequence FRAMES --write-aligned FOLDER [--out STEPS]`` with the ``FAST`` options."""
    out = () if steps is None else ("--out", str(steps))
    return runner.invoke(
        app, ["sequence", *map(str, frames), "--write-aligned", str(folder), *out, "--model-dir", str(model_dir), *FAST]
    )


def pose(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``rotation [3, 3]`` and ``translation [3]`` of the record ``register --out`` wrote."""
    record = json.loads(out.read_text())
    return np.asarray(record["rotation"]), np.asarray(record["translation"])


def post_aligned(
    client: httpx.Client, path: Path, rotation: np.ndarray, translation: np.ndarray, name: str | None = None
) -> httpx.Response:
    """``POST /v1/register/aligned`` of the file at ``path`` (uploaded as ``name``, else its own name) moved by
    ``rotation [3, 3]``, ``translation [3]``."""
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, translation
    return client.post(
        "/v1/register/aligned",
        files={"source": (name or path.name, path.read_bytes())},
        data={"transform": json.dumps(matrix.tolist())},
    )
