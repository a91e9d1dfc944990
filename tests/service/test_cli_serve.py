"""Specification of ``mfgnet serve``: CLI options override ``MFGNET_*`` settings and reach ``run_server``;
and of ``mfgnet register --server`` failures that need no server."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import service
from service.cli import app

runner = CliRunner()
HAS_API = (Path(service.__file__).parent / "api" / "app.py").exists()


@pytest.fixture
def fake_api(monkeypatch) -> dict:
    """Stand-ins for ``service.api.app`` and ``service.core.config`` recording what serve passes."""
    calls: dict = {}

    class Settings:
        def __init__(self, **overrides):
            calls["overrides"] = overrides

    def run_server(settings) -> None:
        calls["settings"] = settings

    monkeypatch.setitem(sys.modules, "service.api.app", types.SimpleNamespace(run_server=run_server))
    monkeypatch.setitem(sys.modules, "service.core.config", types.SimpleNamespace(Settings=Settings))
    return calls


def test_serve_passes_only_the_given_options_and_runs_the_server(fake_api) -> None:
    result = runner.invoke(app, ["serve", "--port", "9100", "--model-dir", "/m/a", "--model-dir", "/m/b"])
    assert result.exit_code == 0, result.output
    assert fake_api["overrides"] == {"port": 9100, "model_dirs": ["/m/a", "/m/b"]}  # the rest comes from the env
    assert "settings" in fake_api


def test_serve_without_options_leaves_everything_to_the_environment(fake_api) -> None:
    assert runner.invoke(app, ["serve"]).exit_code == 0
    assert fake_api["overrides"] == {}


def test_serve_without_the_http_stack_answers_with_the_install_hint(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "service.api.app", None)  # import fails as if fastapi were absent
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert "pip install 'mfgnet[serve]'" in result.stderr and "Traceback" not in result.output


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_cli_options_override_mfgnet_environment_variables(monkeypatch) -> None:
    import service.api.app

    seen = []
    monkeypatch.setattr(service.api.app, "run_server", seen.append)
    monkeypatch.setenv("MFGNET_HOST", "0.0.0.0")
    monkeypatch.setenv("MFGNET_PORT", "9999")
    monkeypatch.setenv("MFGNET_THREADS", "3")
    result = runner.invoke(app, ["serve", "--port", "1234", "--model-dir", "/m/a", "--model-dir", "/m/b"])
    assert result.exit_code == 0, result.output
    (settings,) = seen
    assert settings.port == 1234 and settings.host == "0.0.0.0" and settings.threads == 3
    assert [str(d) for d in settings.model_dirs] == ["/m/a", "/m/b"]


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_invalid_settings_are_reported_without_a_traceback(monkeypatch) -> None:
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    result = runner.invoke(app, ["serve", "--port", "70000"])
    assert result.exit_code == 2
    assert "invalid settings" in result.stderr and "port" in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_models_that_are_not_found_are_reported_without_a_traceback() -> None:
    """``MFGNET_MODELS`` naming a model no folder holds stopped the server with a traceback."""
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_")}, "MFGNET_MODELS": "general,nosuch",
           "MFGNET_PORT": "0"}
    done = subprocess.run([sys.executable, "-c", "from service.cli import main; main()", "serve"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "MFGNET_MODELS names models that were not found: nosuch (found: " in done.stderr
    assert "Traceback" not in done.stderr and "general" in done.stderr


def test_register_against_an_unreachable_server_exits_1(tmp_path) -> None:
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.random.default_rng(0).normal(size=(64, 3)).astype(np.float32))
    result = runner.invoke(app, ["register", str(cloud), str(cloud), "--server", f"http://127.0.0.1:{port}"])
    assert result.exit_code == 1
    assert "cannot reach" in result.stderr and "Traceback" not in result.output


def test_model_dir_is_refused_with_server(tmp_path) -> None:
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.zeros((64, 3), np.float32))
    result = runner.invoke(app, ["register", str(cloud), str(cloud), "--server", "http://x", "--model-dir", "m"])
    assert result.exit_code == 2 and "--model-dir only applies in-process" in result.stderr
