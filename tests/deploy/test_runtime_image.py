"""The container's runtime stage, reproduced without a container engine.

This machine has a docker client but no daemon, so the image's *content* is tested in a fresh
virtual environment built the way the Dockerfile builds the image:

1. the build context is copied through ``.dockerignore`` (the same allow-list docker applies);
2. ``pip wheel --no-deps`` builds the project wheel from it (ONNX models ride along as package data);
3. a new venv gets that wheel with only the ``serve`` extra (installed by ``uv`` where the dev venv has it, else
   pip) -- torch must then be absent;
4. the server starts with the final stage's ``CMD`` argv and ``ENV`` (plus ``MFGNET_HOST`` /
   ``MFGNET_PORT`` for this machine), in an empty working directory, so the bundled models can only
   be found through ``importlib.resources``;
5. the final stage's ``HEALTHCHECK`` command passes, a synthetic pair registers over HTTP, and the
   installed size and the server's RSS / CPU per request are measured and printed.

Run alone (about a minute when pip's cache is warm)::

    pytest tests/deploy/test_runtime_image.py -s

Needs PyPI or a local index for the ``serve`` dependencies; skipped if nothing can be installed.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest
from shapes import bumpy_sphere

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
SITE_PACKAGES_LIMIT_MIB = 400  # measured 329 MiB of runtime packages (scipy + onnxruntime + numpy ~ 280, e57 1.1)
READY_TIMEOUT_S = 180
PIP_TIMEOUT_S = 900
SEED = 20240611
REPORT: dict[str, float | str] = {}  # measurements, printed by the last test


# --------------------------------------------------------------------------------- .dockerignore


def dockerignore_rules(path: Path) -> list[tuple[bool, re.Pattern, str]]:
    """``(negated, regex, pattern)`` per line, in file order (docker: the last matching rule wins)."""
    rules = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negated = line.startswith("!")
        pattern = line[1:].strip() if negated else line
        pattern = pattern.strip("/")
        rules.append((negated, _glob_regex(pattern), pattern))
    return rules


def _glob_regex(pattern: str) -> re.Pattern:
    """Docker's ``filepath.Match`` + ``**`` syntax as a regex over ``/``-separated relative paths."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        elif pattern[i] == "[":
            end = pattern.index("]", i)
            out, i = out + pattern[i : end + 1], end + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out + r"\Z")


def is_ignored(relative: str, rules: list[tuple[bool, re.Pattern, str]]) -> bool:
    """A rule matching the path or any folder above it decides (folders take their contents along)."""
    parts = relative.split("/")
    prefixes = ["/".join(parts[:k]) for k in range(1, len(parts) + 1)]
    ignored = False
    for negated, regex, _ in rules:
        if any(regex.match(prefix) for prefix in prefixes):
            ignored = not negated
    return ignored


def copy_build_context(source: Path, destination: Path) -> list[str]:
    """Copy what ``docker build source`` would send; returns the relative paths copied."""
    rules = dockerignore_rules(source / ".dockerignore")
    reincluded = [pattern for negated, _, pattern in rules if negated]
    copied = []
    for folder, dirs, files in os.walk(source):
        rel_folder = Path(folder).relative_to(source).as_posix()
        rel_folder = "" if rel_folder == "." else rel_folder + "/"
        # prune ignored folders that no '!' rule could reach into (.venv, .git, runs, ...)
        dirs[:] = [d for d in dirs if not is_ignored(rel_folder + d, rules)
                   or any(p.startswith(rel_folder + d + "/") for p in reincluded)]
        for name in files:
            relative = rel_folder + name
            if not is_ignored(relative, rules):
                (destination / relative).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(Path(folder) / name, destination / relative)
                copied.append(relative)
    return sorted(copied)


# ------------------------------------------------------------------------------------ Dockerfile


def final_stage() -> dict:
    """The runtime stage's ``CMD`` argv, ``ENV`` and ``HEALTHCHECK`` argv, parsed with dockerfile-parse."""
    dockerfile_parse = pytest.importorskip("dockerfile_parse")
    parser = dockerfile_parse.DockerfileParser(path=str(DOCKERFILE))
    last_from = max(i for i, item in enumerate(parser.structure) if item["instruction"] == "FROM")
    stage = parser.structure[last_from:]
    cmd = [item["value"] for item in stage if item["instruction"] == "CMD"][-1]
    health = [item["value"] for item in stage if item["instruction"] == "HEALTHCHECK"][-1]
    env: dict[str, str] = {}
    for item in stage:
        if item["instruction"] == "ENV":
            env.update(word.split("=", 1) for word in shlex.split(item["value"]))
    health_argv = json.loads(re.search(r"\bCMD\s+(\[.*\])\s*$", health).group(1))
    return {"cmd": json.loads(cmd), "env": env, "healthcheck": health_argv}


# ------------------------------------------------------------------------------------- fixtures


def _run(argv: list[str], timeout: float, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, **kwargs)


def _dir_mib(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink()) / 2**20


def install_command(python: Path, requirement: str) -> list[str]:
    """Install ``requirement`` into ``python``'s venv: with the uv that ``make install-dev`` puts beside this
    interpreter (the same pinned requirements as pip resolves, in a sixth of the time: decisions/0098), else pip."""
    uv = Path(sys.executable).parent / "uv"
    if uv.is_file():
        return [str(uv), "pip", "install", "--python", str(python), requirement]
    return [str(python), "-m", "pip", "install", "--disable-pip-version-check", requirement]


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    """Build context -> wheel -> fresh venv with ``wheel[serve]``, as the Dockerfile does."""
    if not (ROOT / "service" / "api" / "app.py").is_file():
        pytest.skip("service/api (the HTTP app behind `mfgnet serve`) is not there yet")
    if not list((ROOT / "service" / "models").glob("*/manifest.json")):
        pytest.skip("no exported model in service/models/ to bundle (mfgnet export --out service/models/<name>)")
    started = time.perf_counter()
    work = tmp_path_factory.mktemp("runtime-image")
    context, wheels = work / "context", work / "wheels"
    copied = copy_build_context(ROOT, context)

    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-cache-dir", "-w", str(wheels),
                  str(context)], PIP_TIMEOUT_S)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    (wheel,) = wheels.glob("mfgnet-*.whl")
    REPORT["wheel_kib"] = round(wheel.stat().st_size / 1024, 1)

    venv = work / "venv"
    made = _run([sys.executable, "-m", "venv", str(venv)], 300)
    assert made.returncode == 0, made.stderr
    python = venv / "bin" / "python"
    installed = _run(install_command(python, f"{wheel}[serve]"), PIP_TIMEOUT_S)
    unreachable = (r"No matching distribution|Could not find a version|connection"  # pip's
                   r"|No solution found|Failed to fetch|error sending request|dns error")  # uv's
    if installed.returncode != 0 and re.search(unreachable, installed.stdout + installed.stderr, re.IGNORECASE):
        pytest.skip(f"the serve dependencies cannot be installed here: {installed.stderr[-500:]}")
    assert installed.returncode == 0, installed.stdout[-3000:] + installed.stderr[-3000:]
    site_packages = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              60).stdout.strip())
    REPORT["install_s"] = round(time.perf_counter() - started, 1)
    yield {"context_files": copied, "wheel": wheel, "venv": venv, "python": python,
           "site_packages": site_packages, "work": work}
    shutil.rmtree(venv, ignore_errors=True)  # ~340 MiB; the wheel and server.log stay for inspection


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, timeout: float = 5.0) -> tuple[int, dict]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


def _post_json(url: str, body: dict, timeout: float = 60.0) -> tuple[int, dict]:
    request = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


@pytest.fixture(scope="module")
def server(image) -> dict:
    """The image's CMD with the image's ENV, from an empty working directory, until ready."""
    stage = final_stage()
    port = _free_port()
    cwd = image["work"] / "cwd"
    cwd.mkdir()
    env = {"PATH": f"{image['venv'] / 'bin'}:/usr/local/bin:/usr/bin:/bin", "HOME": str(cwd), "LANG": "C.UTF-8",
           **{k: v for k, v in os.environ.items() if k.startswith("OPENBLAS_")},  # this machine's CPU quirks
           **stage["env"], "MFGNET_HOST": "127.0.0.1", "MFGNET_PORT": str(port)}
    argv = [shutil.which(stage["cmd"][0], path=env["PATH"]) or stage["cmd"][0], *stage["cmd"][1:]]
    assert Path(argv[0]).is_relative_to(image["venv"]), f"CMD {stage['cmd'][0]!r} must come from the venv: {argv[0]}"
    log = (image["work"] / "server.log").open("w")
    started = time.perf_counter()
    process = subprocess.Popen(argv, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while True:
            assert process.poll() is None, f"server exited ({process.returncode}):\n{_tail(log.name)}"
            try:
                if _get(base + "/v2/health/ready", timeout=2)[0] == 200:
                    break
            except (urllib.error.URLError, OSError, ValueError):
                pass
            assert time.monotonic() < deadline, f"not ready in {READY_TIMEOUT_S} s:\n{_tail(log.name)}"
            time.sleep(0.25)
        REPORT["ready_s"] = round(time.perf_counter() - started, 1)
        yield {"base": base, "process": process, "env": env, "cwd": cwd, "healthcheck": stage["healthcheck"]}
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()


def _tail(path: str, chars: int = 4000) -> str:
    return Path(path).read_text()[-chars:]


def synthetic_pair(n: int = 1024, angle_deg: float = 15.0, seed: int = SEED):
    """A smooth closed surface (a bumpy sphere) and its copy moved by a small known rigid motion.

    Returns ``(source [n, 3], target [n, 3], R [3, 3], t [3])`` with ``target = source @ R.T + t``.
    """
    rng = np.random.default_rng(seed)
    source = bumpy_sphere(rng, n)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.deg2rad(angle_deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K
    t = np.array([0.1, -0.05, 0.02])
    return source, source @ R.T + t, R, t


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _rss_mib(pid: int) -> tuple[float, float]:
    status = Path(f"/proc/{pid}/status").read_text()
    current = int(re.search(r"VmRSS:\s+(\d+) kB", status).group(1)) / 1024
    peak = int(re.search(r"VmHWM:\s+(\d+) kB", status).group(1)) / 1024
    return current, peak


# ---------------------------------------------------------------------------------------- tests


def test_build_context_is_the_allow_list(image):
    files = image["context_files"]
    assert "pyproject.toml" in files
    assert any(f.startswith("service/") for f in files)
    leaked = [f for f in files if re.match(r"(\.venv|\.git|runs|tests|docs|data|bench|results)/|model/checkpoints/", f)
              or f.endswith((".pt", ".t7", ".pth", ".pyc"))]
    assert not leaked, f"kept out by .dockerignore, yet in the context: {leaked[:10]}"


def test_wheel_bundles_the_onnx_models_with_their_manifests(image):
    names = zipfile.ZipFile(image["wheel"]).namelist()
    models = {n.split("/")[2] for n in names if re.match(r"service/models/[^/]+/", n)}
    assert models, "no model under service/models/ in the wheel"
    for model in models:
        assert f"service/models/{model}/manifest.json" in names
        assert any(n.startswith(f"service/models/{model}/") and n.endswith(".onnx") for n in names)
    assert not [n for n in names if n.endswith((".pt", ".t7"))], "checkpoints must not ship in the wheel"
    assert not [n for n in names if n.startswith("bench/")], "the benchmarks must not ship in the runtime image"


def test_runtime_has_no_torch_and_no_train_or_dev_extras(image):
    torch = _run([str(image["python"]), "-c", "import torch"], 120)
    assert torch.returncode != 0 and "No module named 'torch'" in torch.stderr
    probe = "import importlib.util as u; print([m for m in ('torch', 'onnx', 'tqdm', 'pytest') if u.find_spec(m)])"
    assert _run([str(image["python"]), "-c", probe], 120).stdout.strip() == "[]"


def test_package_is_imported_from_site_packages_not_the_source_tree(image, server):
    where = _run([str(image["python"]), "-c", "import service.manifest as m; print(m.bundled_models_dir())"], 120,
                 cwd=server["cwd"], env=server["env"])
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()).is_relative_to(image["site_packages"])


def test_healthcheck_command_passes_once_ready(image, server):
    argv = list(server["healthcheck"])
    argv[0] = str(image["venv"] / "bin" / argv[0])
    result = _run(argv, 60, cwd=server["cwd"], env=server["env"])
    assert result.returncode == 0, result.stderr


def test_liveness_answers(server):
    assert _get(server["base"] + "/v2/health/live") == (200, {"live": True})


def test_registers_a_synthetic_pair_over_http(server):
    source, target, R_true, _ = synthetic_pair()
    pid = server["process"].pid
    cpu_before, wall_before = _cpu_seconds(pid), time.perf_counter()
    requests = 5
    for _ in range(requests):
        status, body = _post_json(server["base"] + "/v1/register", {"source": source.tolist(),
                                                                     "target": target.tolist()})
        assert status == 200, body
    REPORT["cpu_s_per_request"] = round((_cpu_seconds(pid) - cpu_before) / requests, 3)
    REPORT["wall_s_per_request"] = round((time.perf_counter() - wall_before) / requests, 3)
    REPORT["rss_mib"], REPORT["rss_peak_mib"] = (round(v, 1) for v in _rss_mib(pid))

    T = np.asarray(body["transform"], dtype=np.float64)
    assert T.shape == (4, 4)
    assert np.allclose(T[3], [0, 0, 0, 1])
    R = T[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-4)
    cos = np.clip((np.trace(R_true.T @ R) - 1) / 2, -1, 1)
    REPORT["rotation_error_deg"] = round(float(np.degrees(np.arccos(cos))), 2)


def test_installed_size_is_bounded_and_report(image, server):
    site = image["site_packages"]
    total = _dir_mib(site)
    scaffolding = sum(_dir_mib(p) for p in site.iterdir()
                      if p.is_dir() and re.match(r"(pip|setuptools|pkg_resources|_distutils_hack)\b", p.name))
    REPORT["site_packages_mib"] = round(total, 1)
    REPORT["runtime_packages_mib"] = round(total - scaffolding, 1)  # without the venv's own pip/setuptools
    largest = sorted(((round(_dir_mib(p), 1), p.name) for p in site.iterdir() if p.is_dir()), reverse=True)[:5]
    REPORT["largest"] = ", ".join(f"{name} {mib}" for mib, name in largest)
    print("\nruntime-image report:", json.dumps(REPORT))
    assert total - scaffolding < SITE_PACKAGES_LIMIT_MIB, REPORT
