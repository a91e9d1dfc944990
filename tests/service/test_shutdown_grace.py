"""A request still running when the server's shutdown grace ends: uvicorn cancels it, and the client gets a JSON 503
with ``Retry-After`` and ``Connection: close`` and the hardening headers, logged and counted as 503. It got uvicorn's
plain-text 500 and was logged with status 0.

A real server (uvicorn in a thread of this process, the service's app with a route added that takes longer than the
grace, real HTTP); the grace is shortened to 0.5 s (the service runs with 5 s)."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import threading
import time

import httpx
import uvicorn
from api_server import isolated_settings, model_root

from service.api.middleware import SHUTDOWN_MESSAGE
from service.core.logging import ACCESS_LOGGER


class Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_a_request_cut_off_by_the_shutdown_grace_gets_a_json_503() -> None:
    from service.api.app import create_app

    app = create_app(isolated_settings(model_dirs=[str(model_root())], bundled_models=False, threads=1))
    started = threading.Event()

    @app.post("/test/slow")
    async def slow() -> dict:
        started.set()
        await asyncio.sleep(30)
        return {}

    records, access = Records(), logging.getLogger(ACCESS_LOGGER)
    level = access.level
    access.addHandler(records)
    access.setLevel(logging.INFO)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", access_log=False, timeout_graceful_shutdown=0.5))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{sock.getsockname()[1]}"
    try:
        for _ in range(200):
            try:
                if httpx.get(f"{url}/v2/health/live", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.05)
        answers: list[httpx.Response | Exception] = []

        def post() -> None:
            try:
                answers.append(httpx.post(f"{url}/test/slow", timeout=20))
            except httpx.HTTPError as exc:
                answers.append(exc)

        client = threading.Thread(target=post)
        client.start()
        assert started.wait(10)
        begun = time.perf_counter()
        server.should_exit = True
        client.join(20)
        thread.join(20)
        assert time.perf_counter() - begun < 5  # the grace, not the route's 30 s
    finally:
        server.should_exit = True
        thread.join(10)
        sock.close()
        access.removeHandler(records)
        access.setLevel(level)
    [response] = answers
    assert isinstance(response, httpx.Response), repr(response)
    assert response.status_code == 503, response.text
    assert response.headers["content-type"] == "application/json"
    assert json.loads(response.text) == {"error": SHUTDOWN_MESSAGE}
    assert response.headers["retry-after"] == "1" and response.headers["connection"] == "close"
    assert response.headers["x-content-type-options"] == "nosniff"  # the hardening headers, as on every answer
    [line] = [r for r in records.records if getattr(r, "path", "") == "/test/slow"]
    assert line.status == 503
