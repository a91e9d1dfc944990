"""ONNX Runtime's Linux build sends telemetry and writes a device id under ``$HOME/.cache/Microsoft`` when it is
imported, unless ``ORT_DISABLE_TELEMETRY`` is set: importing ``service`` sets it (``service/__init__.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def imported_with_home(home: Path, code: str, **env: str) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "ORT_DISABLE_TELEMETRY"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env={**environment, "HOME": str(home), "PYTHONPATH": str(REPO), **env})


@pytest.mark.parametrize("code", ["import service.registrar, onnxruntime", "import bench.graph_ops"],
                         ids=["service", "a benchmark importing onnxruntime itself"])
def test_importing_the_service_keeps_onnxruntime_from_writing_a_device_id(tmp_path, code) -> None:
    done = imported_with_home(tmp_path, code)
    assert done.returncode == 0, done.stderr
    assert not (tmp_path / ".cache").exists() and "telemetry" not in done.stderr


@pytest.mark.parametrize("code", ["import onnxruntime", "import service, onnxruntime"], ids=["bare", "service"])
def test_a_setting_the_environment_names_is_kept(tmp_path, code) -> None:
    """Without the service, or with telemetry asked for by name, ONNX Runtime writes its device id: the test can
    fail."""
    done = imported_with_home(tmp_path, code, **({"ORT_DISABLE_TELEMETRY": "0"} if "service" in code else {}))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / ".cache" / "Microsoft").is_dir()
