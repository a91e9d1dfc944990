"""Shared helpers of the ``test_api_*`` modules: real uvicorn servers, a verified model snapshot, and
seeded ModelNet40 pairs.

Servers are cached per process (one pytest session), so every test module shares them; they are
stopped at exit. The bundled model is copied to a temporary folder and verified first, so a
re-export of ``service/models`` during the test run cannot break the servers.
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import httpx
import numpy as np
import pytest
from shapes import asymmetric_blob
from starlette.requests import Request  # at module level: the held route's annotation is resolved here

from service.manifest import ModelIntegrityError, bundled_models_dir, load_manifest

REPO = Path(__file__).resolve().parents[2]
DATA_DIR = Path(os.environ.get("MFGNET_DATA") or REPO.parent / "shared" / "data" / "modelnet40")
MODEL = "clean"
START_TIMEOUT_S = 60.0
_TMP = Path(tempfile.mkdtemp(prefix="mfgnet-api-tests-"))
atexit.register(shutil.rmtree, _TMP, ignore_errors=True)


# -- model snapshot ----------------------------------------------------------------------------------
@cache
def model_root() -> Path:
    """A folder holding a verified copy of the bundled ``clean`` model (skips if there is none)."""
    source = bundled_models_dir() / MODEL
    root = _TMP / "models"
    for _ in range(10):  # the model may be re-exported while the tests start: copy, then verify the copy
        shutil.rmtree(root, ignore_errors=True)
        try:
            shutil.copytree(source, root / MODEL)
            load_manifest(root / MODEL)
            return root
        except (OSError, ModelIntegrityError):
            time.sleep(3)
    pytest.skip(f"no verified bundled model at {source} (being exported?); the API tests need one")


@cache
def tampered_root() -> Path:
    """A folder with a copy of the model named ``tampered`` whose encoder no longer matches its sha256."""
    root = _TMP / "tampered"
    target = root / "tampered"
    shutil.copytree(model_root() / MODEL, target)
    manifest = json.loads((target / "manifest.json").read_text())
    manifest["name"] = "tampered"
    (target / "manifest.json").write_text(json.dumps(manifest))
    with (target / "encoder.onnx").open("ab") as f:
        f.write(b"\0")
    return root


# -- ModelNet40 pairs ---------------------------------------------------------------------------------
@cache
def _modelnet_points() -> np.ndarray:
    path = DATA_DIR / "modelnet40_test.npz"
    if not path.is_file():
        pytest.skip(f"ModelNet40 test split not found at {path} (set MFGNET_DATA)")
    with np.load(path) as data:
        return data["points"]  # float16 [2468, 1024, 3]


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues: ``[3, 3]`` rotation by ``angle_rad`` about ``axis``."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


@dataclass(frozen=True)
class Pair:
    source: np.ndarray  # float32 [N, 3]
    target: np.ndarray  # float32 [M, 3]
    rotation: np.ndarray  # ground-truth src_to_tgt [3, 3]
    translation: np.ndarray  # [3]


def crop(points: np.ndarray, keep: int, rng: np.random.Generator) -> np.ndarray:
    """The ``keep`` points nearest to a random far-away viewpoint (a partial view)."""
    view = rng.normal(size=3)
    view *= 500 / np.linalg.norm(view)
    return points[np.argsort(np.linalg.norm(points - view, axis=1))[:keep]]


@cache
def modelnet_pair(seed: int = 0, keep: int = 700, max_angle_deg: float = 30.0) -> Pair:
    """A seeded partial-to-partial pair with a known rotation (<= ``max_angle_deg``) and translation."""
    rng = np.random.default_rng(seed)
    shapes = _modelnet_points()
    return _partial_pair(shapes[rng.integers(len(shapes))].astype(np.float64), keep, max_angle_deg, rng)


@cache
def synthetic_pair(seed: int = 0, keep: int = 700, max_angle_deg: float = 30.0) -> Pair:
    """As :func:`modelnet_pair`, from a generated asymmetric shape: for tests that must run without the data."""
    rng = np.random.default_rng(seed)
    return _partial_pair(asymmetric_blob(1024, seed), keep, max_angle_deg, rng)


def _partial_pair(cloud: np.ndarray, keep: int, max_angle_deg: float, rng: np.random.Generator) -> Pair:
    """Two partial views of ``cloud [P, 3]``, the target's moved by a random rotation and translation."""
    R = rotation_about(rng.normal(size=3), np.deg2rad(rng.uniform(0, max_angle_deg)))
    t = rng.uniform(-0.5, 0.5, size=3)
    source = crop(cloud, keep, rng)
    target = crop(cloud @ R.T + t, keep, rng)
    return Pair(source.astype(np.float32), target.astype(np.float32), R, t)


def pair_json(pair: Pair, **options) -> dict:
    return {"source": pair.source.tolist(), "target": pair.target.tolist(), **options}


# -- servers ------------------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Server:
    url: str
    log_path: Path | None = None
    first_ready: httpx.Response | None = None  # the first /v2/health/ready answer after liveness
    stop: object = None
    extra: dict = field(default_factory=dict)

    def client(self, **kwargs) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=60, **kwargs)

    def log_lines(self) -> list[dict]:
        assert self.log_path is not None
        lines = []
        for line in self.log_path.read_text().splitlines():
            try:
                lines.append(json.loads(line))
            except json.JSONDecodeError:
                lines.append({"unparsed": line})
        return lines


def _wait(url: str, proc: subprocess.Popen | None = None, until_ready: bool = True) -> httpx.Response:
    """Poll liveness, then readiness at once (recorded), then until ready; returns the first readiness answer."""
    deadline = time.monotonic() + START_TIMEOUT_S
    first = None
    with httpx.Client(base_url=url, timeout=5) as client:
        while time.monotonic() < deadline:
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"server exited with {proc.returncode}")
            try:
                if first is None:
                    client.get("/v2/health/live").raise_for_status()
                    first = client.get("/v2/health/ready")
                    if first.status_code == 200 or not until_ready:
                        return first
                elif client.get("/v2/health/ready").status_code == 200:
                    return first
            except httpx.TransportError:
                pass
            time.sleep(0.02)
    raise RuntimeError(f"server at {url} not ready within {START_TIMEOUT_S} s")


def start_subprocess_server(name: str, **env: str) -> Server:
    """``run_server()`` in a child process (as in production), settings from ``MFGNET_*`` variables."""
    port = free_port()
    log_path = _TMP / f"{name}.log"
    environ = {
        **{k: v for k, v in os.environ.items() if not k.startswith("MFGNET_") or k == "MFGNET_DATA"},
        "MFGNET_HOST": "127.0.0.1",
        "MFGNET_PORT": str(port),
        "MFGNET_THREADS": "1",
        "MFGNET_BUNDLED_MODELS": "false",
        "MFGNET_MODEL_DIRS": str(model_root()),
        "MFGNET_DEFAULT_MODEL": MODEL,  # the test servers load only this model
        **env,
    }
    code = "from service.api.app import run_server; run_server()"
    with log_path.open("wb") as log:
        proc = subprocess.Popen([sys.executable, "-c", code], env=environ, stdout=log, stderr=subprocess.STDOUT)

    def stop() -> None:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()

    atexit.register(stop)
    url = f"http://127.0.0.1:{port}"
    try:
        first = _wait(url, proc=proc)
    except RuntimeError:
        stop()
        raise RuntimeError(f"{name} server failed to start; log:\n{log_path.read_text()[-3000:]}") from None
    return Server(url, log_path, first, stop, extra={"proc": proc})  # proc: for signals and exit codes


def isolated_settings(**values):
    """``Settings(**values)`` ignoring any ``MFGNET_*`` variables of the developer's shell."""
    from service.core.config import Settings

    saved = {k: os.environ.pop(k) for k in list(os.environ) if k.startswith("MFGNET_")}
    values.setdefault("default_model", MODEL)  # the test servers load only this model
    try:
        return Settings(**values)
    finally:
        os.environ.update(saved)


def start_thread_server(settings, until_ready: bool = True) -> Server:
    """``create_app(settings)`` served by uvicorn in a thread of the test process."""
    from service.api.app import create_app

    return serve_in_thread(create_app(settings), until_ready)


def serve_in_thread(app, until_ready: bool = True) -> Server:
    """``app`` (an ASGI app: a test may add routes to the service's) served by uvicorn in a thread of the test
    process, on a free port of 127.0.0.1; ``stop()`` it when done (at exit otherwise)."""
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()

    def stop() -> None:
        server.should_exit = True
        thread.join(10)
        sock.close()

    atexit.register(stop)
    url = f"http://127.0.0.1:{port}"
    return Server(url, None, _wait(url, until_ready=until_ready), stop)


def held_worker_server(**settings) -> tuple[Server, object, threading.Event]:
    """A real server in a thread with one worker, four places in the queue and ``isolated_settings(**settings)``
    otherwise, whose added route ``POST /test/hold`` holds that worker until the returned event is set: a busy server
    for the checks made before the queue. Returns the server, its limiter (``running``, ``taken``) and the event;
    set the event and ``stop()`` the server when done."""
    from service.api.app import create_app

    app = create_app(isolated_settings(model_dirs=[str(model_root())], bundled_models=False, threads=1,
                                       max_concurrency=1, max_queue=4, **settings))
    release = threading.Event()

    @app.post("/test/hold")
    async def hold(request: Request) -> dict:
        runner = app.state.runner
        with runner.admit() as slot:
            await runner.run(slot, lambda _: None, request, decode=lambda: release.wait(60))
        return {}

    return serve_in_thread(app), app.state.limiter, release


def wait_for(predicate: Callable[[], bool], timeout: float = 30.0, what: str = "condition") -> None:
    """Until ``predicate()`` holds, polled every 20 ms; ``AssertionError`` naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def wait_until_loaded(server: Server) -> None:
    """Until no model is ``loading`` (for servers that never become ready)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    with server.client() as client:
        while time.monotonic() < deadline:
            if all(m["status"] != "loading" for m in client.get("/v1/models").json()["models"]):
                return
            time.sleep(0.05)
    raise RuntimeError("models still loading")


@cache
def main_server() -> Server:
    """Default settings (one ORT thread): most tests run against this one."""
    return start_subprocess_server("main")


LIMITED = {"max_points": 400, "max_file_points": 400, "max_body_bytes": 200_000, "max_batch": 2,
           "api_key": "test-secret-key"}


@cache
def limited_server() -> Server:
    """Small limits, an API key, and no queue: max_concurrency=1, max_queue=0."""
    return start_subprocess_server(
        "limited",
        MFGNET_MAX_POINTS=str(LIMITED["max_points"]),
        MFGNET_MAX_FILE_POINTS=str(LIMITED["max_file_points"]),
        MFGNET_MAX_UPLOAD_BYTES=str(LIMITED["max_body_bytes"]),
        MFGNET_MAX_BODY_BYTES=str(LIMITED["max_body_bytes"]),
        MFGNET_MAX_BATCH=str(LIMITED["max_batch"]),
        MFGNET_API_KEY=LIMITED["api_key"],
        MFGNET_MAX_CONCURRENCY="1",
        MFGNET_MAX_QUEUE="0",
    )


def assert_error(response: httpx.Response, status: int, *words: str) -> dict:
    """``response`` is the JSON error ``{"error": ...}`` with ``status`` and mentions each of ``words``."""
    assert response.status_code == status, (response.status_code, response.text[:500])
    assert response.headers["content-type"].startswith("application/json")
    body = response.json()
    assert isinstance(body.get("error"), str) and body["error"]
    for word in words:
        assert word.lower() in body["error"].lower(), body["error"]
    text = response.text
    assert "Traceback" not in text and str(REPO) not in text and "/site-packages/" not in text
    return body
