"""ONNX Runtime's Linux build sends telemetry and writes a device id under ``$XDG_CACHE_HOME/Microsoft`` (by default
``$HOME/.cache/Microsoft``) when it is imported, unless ``ORT_DISABLE_TELEMETRY`` is set: importing ``service`` sets it
(``service/__init__.py``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def imported_with_home(home: Path, code: str, **env: str) -> subprocess.CompletedProcess:
    """Run ``code`` with ``home`` as both ``$HOME`` and ``$XDG_CACHE_HOME``'s parent, so a device id lands in it.

    The environment is otherwise only ``PATH``: ONNX Runtime writes nothing where it sees a CI machine (``CI``,
    ``GITHUB_ACTIONS``, ``JENKINS_URL`` and the like) or its own unit tests, and a CI machine's variables would make the
    control below pass or fail by where it runs."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env={"PATH": os.environ.get("PATH", ""), "HOME": str(home),
                               "XDG_CACHE_HOME": str(home / ".cache"), "PYTHONPATH": str(REPO), **env})


def written_under(home: Path) -> list[str]:
    return sorted(str(path.relative_to(home)) for path in home.rglob("*"))


@pytest.mark.parametrize("code", ["import service.registrar, onnxruntime", "import bench.graph_ops"],
                         ids=["service", "a benchmark importing onnxruntime itself"])
def test_importing_the_service_keeps_onnxruntime_from_writing_a_device_id(tmp_path, code) -> None:
    done = imported_with_home(tmp_path, code)
    assert done.returncode == 0, done.stderr
    assert written_under(tmp_path) == [] and "telemetry" not in done.stderr


@pytest.mark.parametrize("code", ["import onnxruntime", "import service, onnxruntime"], ids=["bare", "service"])
def test_a_setting_the_environment_names_is_kept(tmp_path, code) -> None:
    """Without the service, or with telemetry asked for by name, ONNX Runtime writes its device id: the test can
    fail."""
    done = imported_with_home(tmp_path, code, **({"ORT_DISABLE_TELEMETRY": "0"} if "service" in code else {}))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / ".cache" / "Microsoft").is_dir(), written_under(tmp_path)
