"""Bad files for the training-side commands' usage-error tests, and the check of their answer.

Import as ``from bad_files import ...`` (``tests/helpers`` is on ``sys.path``; see ``shapes.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# what each kind of bad file is, and a word the command's message must hold about it
NOT_A_FILE = {"missing": "no such file", "folder": "a folder, not a file"}
NOT_A_CHECKPOINT = {"random": "not a PyTorch checkpoint", "empty": "not a PyTorch checkpoint (empty)",
                    "text": "not a PyTorch checkpoint"}
NOT_AN_NPZ = {"random": "not an .npz archive", "empty": "empty", "text": "not an .npz archive",
              "npy": "not an .npz archive"}
NOT_A_MODEL = {"missing": "no such model folder", "unknown-name": "nor a bundled model", "empty": "nor a bundled model",
               "file": "a file, not a model folder", "no-manifest": "manifest.json is missing",
               "damaged-manifest": "malformed manifest.json"}


def bad_file(tmp_path: Path, kind: str) -> Path:
    """A path under ``tmp_path`` that is ``kind``: missing, folder, random (bytes), empty, text or npy."""
    path = tmp_path / f"bad_{kind}.bin"
    if kind == "folder":
        path.mkdir()
    elif kind == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("source,target\n1,2\n")
    elif kind == "npy":
        np.save(path.with_suffix(".npy"), np.zeros((2, 3)))
        path = path.with_suffix(".npy")
    return path


def bad_model(tmp_path: Path, kind: str) -> str:
    """A ``--model`` under ``tmp_path`` that is ``kind``: missing, unknown-name (no bundled model of that name),
    empty, file, no-manifest (a folder of a graph without one) or damaged-manifest."""
    if kind == "missing":
        return str(tmp_path / "none")
    if kind == "unknown-name":
        return "nosuch"
    if kind == "empty":  # named the folder of bundled models
        return ""
    if kind == "file":
        (tmp_path / "model.onnx").write_bytes(b"onnx?")
        return str(tmp_path / "model.onnx")
    folder = tmp_path / "m"
    folder.mkdir()
    if kind == "no-manifest":
        (folder / "encoder.onnx").write_bytes(b"onnx?")
    else:
        (folder / "manifest.json").write_text("{not json")
    return str(folder)


def assert_usage_error(result: object, *words: str) -> str:
    """``result`` (CliRunner's) is exit code 2 with one ``mfgnet: error:`` line holding ``words``; that line."""
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mfgnet: error: "), result.stderr
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]
