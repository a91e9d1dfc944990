"""Specification of ``mfgnet serve``: CLI options override ``MFGNET_*`` settings and reach ``run_server``;
and of ``mfgnet register --server`` failures that need no server."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from api_server import free_port
from typer.testing import CliRunner

import service
from service.cli import app

runner = CliRunner()
HAS_API = (Path(service.__file__).parent / "api" / "app.py").exists()


def serve(args: list[str], **env: str) -> subprocess.Popen:
    """``mfgnet serve ARGS`` in a child process, with only these ``MFGNET_*`` variables."""
    environ = {**{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_")}, "MFGNET_HOST": "127.0.0.1",
               "MFGNET_THREADS": "1", **env}
    return subprocess.Popen([sys.executable, "-c", "from service.cli import main; main()", "serve", *args],
                            env=environ, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def served_models(proc: subprocess.Popen, port: int) -> list[str]:
    """The model names ``/v1/models`` lists on ``port`` once the server there is live; the server is stopped."""
    import httpx

    try:
        for _ in range(300):
            assert proc.poll() is None, f"the server exited with {proc.returncode}"
            try:
                models = httpx.get(f"http://127.0.0.1:{port}/v1/models", timeout=2)
                return sorted(m["name"] for m in models.json()["models"])
            except httpx.TransportError:
                time.sleep(0.1)
        raise AssertionError(f"nothing answered on port {port}")
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_serve_options_override_the_environment_and_the_rest_comes_from_it(tmp_path) -> None:
    """``--port`` and ``--model-dir`` win over MFGNET_PORT and MFGNET_MODEL_DIRS; MFGNET_BUNDLED_MODELS, which has no
    option, comes from the environment; without options the environment says everything."""
    from service.manifest import bundled_models_dir

    if not (bundled_models_dir() / "clean").is_dir():
        pytest.skip("needs the bundled clean model")
    shutil.copytree(bundled_models_dir() / "clean", tmp_path / "mine")
    env_port, option_port = free_port(), free_port()
    proc = serve(["--port", str(option_port), "--model-dir", str(tmp_path)], MFGNET_PORT=str(env_port),
                 MFGNET_MODEL_DIRS="/nowhere", MFGNET_BUNDLED_MODELS="false")
    assert served_models(proc, option_port) == ["mine"]
    proc = serve([], MFGNET_PORT=str(env_port), MFGNET_MODEL_DIRS=str(tmp_path), MFGNET_BUNDLED_MODELS="false")
    assert served_models(proc, env_port) == ["mine"]


def test_serve_without_the_http_stack_answers_with_the_install_hint(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "service.api.app", None)  # import fails as if fastapi were absent
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert "pip install 'mfgnet[serve]'" in result.stderr and "Traceback" not in result.output


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_cli_options_override_mfgnet_environment_variables(monkeypatch, tmp_path) -> None:
    import service.api.app

    seen = []
    monkeypatch.setattr(service.api.app, "run_server", seen.append)
    monkeypatch.setenv("MFGNET_HOST", "0.0.0.0")
    monkeypatch.setenv("MFGNET_PORT", "9999")
    monkeypatch.setenv("MFGNET_THREADS", "3")
    for folder in ("a", "b"):  # a model folder each (its manifest is read once the server starts)
        (tmp_path / folder / "mine").mkdir(parents=True)
        (tmp_path / folder / "mine" / "manifest.json").write_text("{}")
    result = runner.invoke(app, ["serve", "--port", "1234", "--model-dir", str(tmp_path / "a"),
                                 "--model-dir", str(tmp_path / "b")])
    assert result.exit_code == 0, result.output
    (settings,) = seen
    assert settings.port == 1234 and settings.host == "0.0.0.0" and settings.threads == 3
    assert [str(d) for d in settings.model_dirs] == [str(tmp_path / "a"), str(tmp_path / "b")]


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_a_host_name_that_does_not_resolve_stops_serve(monkeypatch) -> None:
    """``MFGNET_HOST=not.a.host.invalid`` aborted the process (exit 134) once the models had begun to load."""
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    result = runner.invoke(app, ["serve", "--host", "not.a.host.invalid"])
    assert result.exit_code == 2
    assert "MFGNET_HOST / --host 'not.a.host.invalid': " in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
@pytest.mark.parametrize("where", ["option", "environment"])
def test_a_model_folder_that_is_not_there_stops_serve(monkeypatch, tmp_path, where) -> None:
    """``--model-dir`` or ``MFGNET_MODEL_DIRS`` naming no folder served the bundled models alone, silently (``mfgnet
    register`` and ``mfgnet models`` refuse it)."""
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    (tmp_path / "here").mkdir()
    missing = tmp_path / "not_here"
    if where == "option":
        result = runner.invoke(app, ["serve", "--model-dir", str(tmp_path / "here"), "--model-dir", str(missing)])
    else:
        monkeypatch.setenv("MFGNET_MODEL_DIRS", f"{tmp_path / 'here'},{missing}")
        result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert f"model folder {missing}: not a folder (--model-dir or MFGNET_MODEL_DIRS)" in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_invalid_settings_are_reported_without_a_traceback(monkeypatch) -> None:
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    result = runner.invoke(app, ["serve", "--port", "70000"])
    assert result.exit_code == 2
    assert ("invalid settings: MFGNET_PORT / --port: Input should be less than or equal to 65535 (got 70000)"
            in result.stderr)  # the option as well as the variable: it was given as the option
    monkeypatch.setenv("MFGNET_MAX_QUEUE", "many")
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert "invalid settings: MFGNET_MAX_QUEUE: Input should be a valid integer" in result.stderr
    assert "(got 'many')" in result.stderr and "pydantic.dev" not in result.stderr  # one line, no URL
    monkeypatch.delenv("MFGNET_MAX_QUEUE")
    monkeypatch.setenv("MFGNET_LOG_LEVEL", "verbose")  # was a traceback from logging, exit 1
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert ("invalid settings: MFGNET_LOG_LEVEL: expected one of debug, info, warning, error, critical (got "
            "'verbose')") in result.stderr


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


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_a_default_model_the_server_does_not_serve_stops_it() -> None:
    """``MFGNET_MODELS`` without ``MFGNET_DEFAULT_MODEL``'s model (``general`` by default) started a server that was
    ready and answered every request naming no model, the page's among them, with a 404."""
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_")}, "MFGNET_MODELS": "clean,noise",
           "MFGNET_PORT": "0"}
    done = subprocess.run([sys.executable, "-c", "from service.cli import main; main()", "serve"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "MFGNET_DEFAULT_MODEL is 'general', which this server does not serve (it serves clean, noise)" in done.stderr
    assert "Traceback" not in done.stderr


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


@pytest.mark.parametrize("command", ["register", "sequence"])
@pytest.mark.parametrize(("args", "flag"), [
    (["--timeout", "5"], "--timeout"), (["--busy-retries", "0"], "--busy-retries"),
    (["--no-binary"], "--binary/--no-binary"), (["--api-key", "k"], "--api-key")])
def test_a_servers_client_options_are_refused_without_server(tmp_path, monkeypatch, command, args, flag) -> None:
    """They were silently ignored in process, while in-process options with --server are refused. An API key from
    MFGNET_API_KEY is not refused: the variable may be set for other runs."""
    if command == "sequence" and flag.startswith("--binary"):
        pytest.skip("mfgnet sequence always uploads .npy files")
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.zeros((64, 3), np.float32))
    result = runner.invoke(app, [command, str(cloud), str(cloud), *args])
    assert result.exit_code == 2 and f"{flag} only applies with --server" in result.stderr, result.output
    monkeypatch.setenv("MFGNET_API_KEY", "k")
    result = runner.invoke(app, [command, str(cloud), str(cloud), "--json"] if command == "register" else
                           [command, str(cloud), str(cloud)])
    assert "only applies with --server" not in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
@pytest.mark.parametrize(("variable", "value", "words"), [
    ("MFGNET_API_KEY", "s3cret\n", "MFGNET_API_KEY: must be printable ASCII"),  # a Secret made from a file
    ("MFGNET_API_KEY", "clé", "MFGNET_API_KEY: must be printable ASCII"),
    ("MFGNET_TIMEOUT_S", "inf", "MFGNET_TIMEOUT_S: Input should be a finite number"),
    ("MFGNET_BODY_TIMEOUT_S", "inf", "MFGNET_BODY_TIMEOUT_S: Input should be a finite number"),
    ("MFGNET_HEADER_TIMEOUT_S", "inf", "MFGNET_HEADER_TIMEOUT_S: Input should be a finite number"),
])
def test_a_setting_no_request_could_meet_stops_serve(monkeypatch, variable, value, words) -> None:
    """A key with a line break or a non-ASCII letter started a ready server that answered every request 401 (no
    client can send it); an infinite deadline turned the deadline, or the slowloris guard, off without a word."""
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    monkeypatch.setenv(variable, value)
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2 and words in result.stderr, result.stderr
    assert "s3cret" not in result.stderr and "clé" not in result.stderr  # a key's value is never printed


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_a_model_folder_without_a_model_stops_serve(monkeypatch, tmp_path) -> None:
    """An empty (or mis-mounted) MFGNET_MODEL_DIRS folder was accepted: the server served the bundled models alone,
    or, without them, stayed live and never ready, with no line saying why."""
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    (tmp_path / "empty" / "nothing_here").mkdir(parents=True)
    monkeypatch.setenv("MFGNET_MODEL_DIRS", str(tmp_path / "empty"))
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert f"model folder {tmp_path / 'empty'}: no model in it" in result.stderr


@pytest.mark.skipif(not HAS_API or os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to read as a user without the permission override")
def test_a_model_folder_the_server_cannot_read_stops_it_in_one_line(tmp_path) -> None:
    """A volume of another owner (uid 10001 in the image) ended start-up in a 94-line PermissionError traceback."""
    folder = tmp_path / "unreadable"
    folder.mkdir()
    folder.chmod(0)
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_")}, "MFGNET_MODEL_DIRS": str(folder),
           "MFGNET_PORT": "0"}
    done = subprocess.run(["setpriv", "--bounding-set", "-dac_override,-dac_read_search", sys.executable, "-c",
                           "from service.cli import main; main()", "serve"], env=env, capture_output=True, text=True,
                          timeout=60)
    folder.chmod(0o755)
    assert done.returncode == 2, done.stderr
    assert f"model folder {folder}" in done.stderr and "Permission denied" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_serve_with_no_model_at_all_stops(monkeypatch) -> None:
    """It started, answered readiness with 503 for ever and logged nothing."""
    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    monkeypatch.setenv("MFGNET_BUNDLED_MODELS", "false")
    monkeypatch.delenv("MFGNET_MODEL_DIRS", raising=False)
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert "no model to serve: MFGNET_BUNDLED_MODELS is false and MFGNET_MODEL_DIRS (--model-dir) names no folder" \
        in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_serve_without_a_writable_temporary_folder_stops(monkeypatch, tmp_path) -> None:
    """A read-only root filesystem without a /tmp volume: the server was ready, and every upload past 1 MiB a 500."""
    import tempfile

    import service.api.app

    monkeypatch.setattr(service.api.app, "run_server", lambda settings: pytest.fail("must not start"))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "gone"))
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2
    assert f"no writable temporary folder ({tmp_path / 'gone'}: No such file or directory; TMPDIR, else /tmp)" \
        in result.stderr
    # none of Python's candidate folders writable: gettempdir() itself raises, and naming the folder raised again
    monkeypatch.setattr(tempfile, "tempdir", None)
    monkeypatch.setattr(tempfile, "_candidate_tempdir_list", lambda: [str(tmp_path / "gone")])
    monkeypatch.setenv("TMPDIR", str(tmp_path / "gone"))
    result = runner.invoke(app, ["serve"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert f"no writable temporary folder ({tmp_path / 'gone'}: No usable temporary directory found" in result.stderr


@pytest.mark.skipif(not HAS_API, reason="service/api/app.py does not exist yet")
def test_a_default_model_set_by_name_and_not_served_stops_serve_also_beside_one_model() -> None:
    """With one model served, MFGNET_DEFAULT_MODEL=noise was replaced by it without a word."""
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_")}, "MFGNET_MODELS": "general",
           "MFGNET_DEFAULT_MODEL": "noise", "MFGNET_PORT": "0"}
    done = subprocess.run([sys.executable, "-c", "from service.cli import main; main()", "serve"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "MFGNET_DEFAULT_MODEL is 'noise', which this server does not serve (it serves general)" in done.stderr
