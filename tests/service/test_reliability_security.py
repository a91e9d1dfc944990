"""Security defaults: limits on by default, constant-time API-key comparison, CORS off, request ids,
and JSON logs that never carry point data.

Covered elsewhere and not repeated here: the API key on every inference route and open health routes
(``test_api_limits.py``), request ids echoed or generated (``test_api_health.py``), and no traceback or
internal path in any error body (every case of ``test_reliability_battery.py`` and every fuzzed
response in ``test_reliability_fuzz.py``).
"""

from __future__ import annotations

import json
import math
import re

import httpx
import numpy as np
import pytest
from api_server import isolated_settings, main_server, modelnet_pair, serve_in_thread

from service.api import deps
from service.api.app import create_app

ORIGIN = "https://attacker.example"


def test_size_and_time_limits_are_on_by_default():
    settings = isolated_settings()
    assert 0 < settings.max_body_bytes <= 256 * 1024 * 1024
    assert 32 <= settings.max_points <= 1_000_000
    assert 0 < settings.timeout_s < math.inf and 0 < settings.body_timeout_s <= 60 and settings.body_min_rate >= 1024
    assert settings.max_queue < 1_000 and settings.max_batch <= 64
    assert settings.cors_origins == [] and settings.api_key is None  # CORS off; the key is opt-in


def test_api_key_is_compared_in_constant_time(monkeypatch):
    """The bearer token goes through ``hmac.compare_digest`` (never ``==``), wrong or right."""
    calls = []

    def spy(given: bytes, expected: bytes) -> bool:
        calls.append((given, expected))
        return given == expected

    monkeypatch.setattr(deps.hmac, "compare_digest", spy)
    server = serve_in_thread(create_app(isolated_settings(bundled_models=False, model_dirs=[], api_key="s3cret-key")),
                             until_ready=False)  # in this process: the spy sees the server's comparisons
    try:
        with server.client() as client:
            def ask(key: str) -> httpx.Response:
                return client.post("/v1/register", json={}, headers={"Authorization": f"Bearer {key}"})

            assert ask("wrong").status_code == 401
            assert ask("s3cret-key").status_code != 401
    finally:
        server.stop()
    assert calls == [(b"wrong", b"s3cret-key"), (b"s3cret-key", b"s3cret-key")]


def test_cross_origin_requests_get_no_cors_headers_by_default():
    with main_server().client(headers={"Origin": ORIGIN}) as client:
        for response in (
            client.get("/v1/models"),
            client.post("/v1/register", json={}),
            client.options("/v1/register", headers={"Access-Control-Request-Method": "POST"}),
        ):
            assert not any(h.lower().startswith("access-control-") for h in response.headers), response.headers


def test_every_response_carries_a_request_id():
    with main_server().client() as client:
        for response in (client.get("/v2/health/ready"), client.post("/v1/register", content=b"{"),
                         client.get("/nope"), client.post("/v1/register", json={}),
                         client.post("/v1/register", content=b"x", headers={"content-type": "text/plain"})):
            assert re.fullmatch(r"[0-9a-f]{32}", response.headers["x-request-id"]), response.headers


def test_server_log_is_json_lines_without_any_coordinates():
    """The server's stderr after a registration, a rejected cloud and a malformed body holds none of their points."""
    server = main_server()
    pair = modelnet_pair(4)
    source = pair.source.astype(np.float64) + 12.3456789  # distinctive digits
    target = pair.target.astype(np.float64) - 98.7654321
    body = {"source": source.tolist(), "target": target.tolist(), "iterations": 1, "keypoints": 16}
    bad = {**body, "source": [[float("nan"), *source[0, 1:].tolist()], *source[1:].tolist()]}
    with server.client() as client:
        assert client.post("/v1/register", json=body).status_code == 200
        assert client.post("/v1/register", content=json.dumps(bad), headers={"content-type": "application/json"}
                           ).status_code == 422
        assert client.post("/v1/register", content=json.dumps(body)[:5000],
                           headers={"content-type": "application/json"}).status_code == 400
        client.get("/v2/health/live")
    text = server.log_path.read_text()
    for line in text.splitlines():  # every line is one JSON object
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            pytest.fail(f"not a JSON line in the server log: {line[:300]!r}")
        assert isinstance(record, dict), line[:300]
    for value in (*source[:50].ravel(), *target[:50].ravel()):
        for shown in (repr(float(value)), f"{value:.6f}"):
            assert shown not in text, shown
    assert "12.3456" not in text and "98.7654" not in text
