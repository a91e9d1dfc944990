"""Specification of the request middleware on an app with a route that fails (no model): the last-resort JSON 500,
request ids and the body limit, over real HTTP to uvicorn in a thread of the test process (so that the test sees
the server's log records)."""

from __future__ import annotations

import logging

import httpx
from api_server import isolated_settings, serve_in_thread

from service.api.app import create_app


def app_with_failing_route(**settings):
    app = create_app(isolated_settings(bundled_models=False, model_dirs=[], **settings))

    @app.get("/boom")
    async def boom():
        raise RuntimeError("secret detail at /srv/internal/path.py")

    return app


def request(app, method: str, path: str, **kwargs) -> httpx.Response:
    server = serve_in_thread(app, until_ready=False)
    try:
        with httpx.Client(base_url=server.url, timeout=10) as client:
            return client.request(method, path, **kwargs)
    finally:
        server.stop()


def test_unexpected_error_is_a_generic_json_500_and_the_traceback_is_logged(caplog):
    with caplog.at_level(logging.ERROR, logger="mfgnet.api"):
        response = request(app_with_failing_route(), "GET", "/boom", headers={"X-Request-ID": "r-1"})
    assert response.status_code == 500
    assert response.json() == {"error": "internal server error", "request_id": "r-1"}
    assert response.headers["x-request-id"] == "r-1"
    assert "secret detail" not in response.text
    assert any(record.exc_info and "secret detail" in str(record.exc_info[1]) for record in caplog.records)


def test_content_length_over_the_limit_is_refused_before_routing():
    app = app_with_failing_route(max_body_bytes=2048)
    response = request(app, "POST", "/boom", content=b"x" * 4096)  # even a route that would fail
    assert response.status_code == 413
    assert "MFGNET_MAX_BODY_BYTES" in response.json()["error"]


def test_readiness_without_models_explains_why():
    response = request(app_with_failing_route(), "GET", "/v2/health/ready")
    assert response.status_code == 503
    assert "no model" in response.json()["error"]
