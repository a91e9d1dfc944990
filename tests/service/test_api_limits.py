"""Specification of the limits and protections: request size (413), API key (401), overload (503 with
Retry-After, never 500), deadline (504), and readiness when a model is tampered with."""

from __future__ import annotations

import io
import json
import socket
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlsplit

import numpy as np
import pytest
from api_server import (
    LIMITED,
    MODEL,
    assert_error,
    isolated_settings,
    limited_server,
    model_root,
    modelnet_pair,
    pair_json,
    start_thread_server,
    tampered_root,
    wait_until_loaded,
)
from openapi_check import assert_conforms

KEY = LIMITED["api_key"]
AUTH = {"Authorization": f"Bearer {KEY}"}
CORS_ORIGIN = "https://viewer.example"
SMALL = 300  # points per cloud: under the limited server's max_points


@pytest.fixture(scope="session")
def server():
    return limited_server()


@pytest.fixture(scope="session")
def client(server):
    with server.client(headers=AUTH) as c:
        yield c


def small_pair(**options) -> dict:
    pair = modelnet_pair(1)
    return {"source": pair.source[:SMALL].tolist(), "target": pair.target[:SMALL].tolist(), **options}


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def test_small_request_passes(client):
    assert client.post("/v1/register", json=small_pair(iterations=1)).status_code == 200


def test_too_many_points_is_413_for_json_multipart_and_oip(client):
    big = np.random.default_rng(0).normal(size=(LIMITED["max_points"] + 1, 3)).astype(np.float32)
    small = np.asarray(small_pair()["source"], dtype=np.float32)
    body = {"source": big.tolist(), "target": small.tolist()}
    assert_error(client.post("/v1/register", json=body), 413, "source", str(LIMITED["max_points"]))
    files = {"source": ("s.npy", npy(small)), "target": ("t.npy", npy(big))}
    assert_error(client.post("/v1/register", files=files), 413, "target")
    infer = {"inputs": [
        {"name": "SOURCE", "shape": list(big.shape), "datatype": "FP32", "data": big.ravel().tolist()},
        {"name": "TARGET", "shape": list(small.shape), "datatype": "FP32", "data": small.ravel().tolist()},
    ]}
    assert_error(client.post(f"/v2/models/{MODEL}/infer", json=infer), 413, "SOURCE")
    assert client.post("/v1/register", json=small_pair(iterations=1)).status_code == 200


def test_body_over_max_body_bytes_is_413_before_reading_it(client):
    body = b'{"source": [' + b"[0.0, 0.0, 0.0]," * (LIMITED["max_body_bytes"] // 15) + b"]}"
    response = client.post("/v1/register", content=body, headers={"content-type": "application/json"})
    assert_error(response, 413, "MFGNET_MAX_BODY_BYTES")


def test_body_over_limit_without_content_length_is_413(client):
    chunk = b"[0.0, 0.0, 0.0]," * 1000

    def stream():
        yield b'{"source": ['
        for _ in range(LIMITED["max_body_bytes"] // len(chunk) + 2):
            yield chunk

    response = client.post("/v1/register", content=stream(), headers={"content-type": "application/json"})
    assert_error(response, 413, "MFGNET_MAX_BODY_BYTES")


def test_too_many_batch_pairs_is_413(client):
    pairs = [small_pair()] * (LIMITED["max_batch"] + 1)
    assert_error(client.post("/v1/register/batch", json={"pairs": pairs}), 413, "MFGNET_MAX_BATCH")


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": KEY},
                                     {"Authorization": f"Basic {KEY}"}])
def test_inference_needs_the_api_key(server, headers):
    with server.client() as anonymous:
        for path in ("/v1/register", "/v1/register/batch", f"/v2/models/{MODEL}/infer"):
            response = anonymous.post(path, json=small_pair(), headers=headers)
            assert_error(response, 401, "api key")
            assert response.headers["www-authenticate"] == "Bearer"


def test_health_and_metadata_stay_open_with_an_api_key(server):
    with server.client() as anonymous:
        for path in ("/v2/health/live", "/v2/health/ready", "/v2", f"/v2/models/{MODEL}",
                     f"/v2/models/{MODEL}/ready", "/v1/models", "/metrics", "/openapi.json"):
            assert anonymous.get(path).status_code == 200, path


def test_overload_gets_503_with_retry_after_and_never_500(server, client):
    def post(_):
        with server.client(headers=AUTH) as c:
            return c.post("/v1/register", json=small_pair())

    with ThreadPoolExecutor(6) as pool:
        responses = list(pool.map(post, range(6)))
    statuses = sorted(r.status_code for r in responses)
    assert set(statuses) <= {200, 503}, statuses
    assert 200 in statuses and 503 in statuses, statuses
    doc = client.get("/openapi.json").json()
    for response in responses:
        if response.status_code == 503:
            assert_error(response, 503, "busy")
            assert int(response.headers["retry-after"]) >= 1
            assert_conforms(doc, "POST", "/v1/register", response)
    assert client.post("/v1/register", json=small_pair(iterations=1)).status_code == 200
    assert 'status="500"' not in client.get("/metrics").text


def test_cors_is_off_by_default(client):
    response = client.options("/v1/register", headers={"Origin": CORS_ORIGIN, "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in response.headers


@pytest.fixture(scope="session")
def strict_server():
    """In-process server: a tampered model next to the good one, strict readiness, a tiny deadline."""
    settings = isolated_settings(
        model_dirs=[str(model_root()), str(tampered_root())],
        bundled_models=False,
        threads=1,
        timeout_s=0.001,
        strict_readiness=True,
        cors_origins=[CORS_ORIGIN],
    )
    server = start_thread_server(settings, until_ready=False)
    wait_until_loaded(server)
    yield server
    server.stop()


def test_tampered_model_is_not_served_and_keeps_the_reason(strict_server):
    with strict_server.client() as c:
        ready = c.get("/v2/health/ready")
        assert_error(ready, 503, "tampered", "failed")
        models = {m["name"]: m for m in c.get("/v1/models").json()["models"]}
        assert models[MODEL]["status"] == "ready"
        assert models["tampered"]["status"] == "failed" and "sha256" in models["tampered"]["error"]
        assert_error(c.get("/v2/models/tampered/ready"), 503, "tampered")
        # a registration naming it answers 503 too, but only within this server's 1 ms deadline (504 when the
        # worker starts late, as under two test workers): tests/service/test_reliability_faults.py checks it


def test_oip_clients_read_the_not_ready_answers_as_false(strict_server):
    """tritonclient reads readiness as ``status == 200`` (KServe's client raises on any non-2xx, as Kubernetes
    probes fail on one): the not-ready 503 is False, not an error, and a 200 saying ``ready: false`` would be
    True to it."""
    import tritonclient.http as httpclient  # the dev extra's stock OIP client

    triton = httpclient.InferenceServerClient(strict_server.url.removeprefix("http://"))
    try:
        assert triton.is_server_live()
        assert triton.is_server_ready() is False
        assert triton.is_model_ready("tampered") is False
        assert triton.is_model_ready("no-such-model") is False
        assert triton.is_model_ready(MODEL) is True
    finally:
        triton.close()


def test_past_the_deadline_is_504(strict_server):
    with strict_server.client() as c:
        assert_error(c.post("/v1/register", json=small_pair()), 504, "MFGNET_TIMEOUT_S")


SHORT_DEADLINE_S = 0.02  # the short-deadline server's: time to start a worker, but not to parse the clouds below
SHORT_DEADLINE_POINTS = 100_000  # its max_points: a cloud one over takes over 0.1 s to parse


@pytest.fixture(scope="module")
def short_deadline_server():
    """In-process server whose deadline is shorter than reading a cloud over its max_points out of a body."""
    settings = isolated_settings(model_dirs=[str(model_root())], bundled_models=False, threads=1,
                                 timeout_s=SHORT_DEADLINE_S, max_points=SHORT_DEADLINE_POINTS,
                                 max_file_points=SHORT_DEADLINE_POINTS)
    server = start_thread_server(settings)
    yield server
    server.stop()


def test_too_many_points_is_413_whatever_the_deadline(short_deadline_server):
    """A cloud over max_points was counted while the deadline ran: with a deadline shorter than the parse it was a
    504. Each body is refused from its size (413 naming the cloud) on every route; a registration within the limits
    still meets the deadline (504)."""
    rng = np.random.default_rng(0)
    big = rng.normal(size=(SHORT_DEADLINE_POINTS + 1, 3)).astype(np.float32)
    small = rng.normal(size=(SMALL, 3)).astype(np.float32)
    pair = {"source": big.tolist(), "target": small.tolist()}
    infer = {"inputs": [
        {"name": "SOURCE", "shape": list(big.shape), "datatype": "FP32", "data": big.ravel().tolist()},
        {"name": "TARGET", "shape": list(small.shape), "datatype": "FP32", "data": small.ravel().tolist()},
    ]}
    with short_deadline_server.client() as c:
        assert_error(c.post("/v1/register", json=pair), 413, "source", str(SHORT_DEADLINE_POINTS))
        assert_error(c.post("/v1/register/batch", json={"pairs": [pair]}), 413, "pairs[0].source")
        files = {"source": ("s.npy", npy(small)), "target": ("t.npy", npy(big))}
        assert_error(c.post("/v1/register", files=files), 413, "target")
        assert_error(c.post("/v1/register/view", files=files), 413, "target")
        aligned = {"transform": json.dumps(np.eye(4).tolist())}
        assert_error(c.post("/v1/register/aligned", files={"source": files["target"]}, data=aligned), 413, "source")
        assert_error(c.post(f"/v2/models/{MODEL}/infer", json=infer), 413, "SOURCE")
        assert_error(c.post("/v1/register", json=pair_json(modelnet_pair(1))), 504, "MFGNET_TIMEOUT_S")


def test_not_ready_and_deadline_answers_match_the_openapi_document(strict_server):
    with strict_server.client() as c:
        doc = c.get("/openapi.json").json()
        ready = c.get("/v2/health/ready")
        assert ready.status_code == 503 and ready.json()["models"]["tampered"] == "failed"
        assert_conforms(doc, "GET", "/v2/health/ready", ready)
        assert_conforms(doc, "GET", "/v2/models/{name}/ready", c.get("/v2/models/tampered/ready"))  # 503
        late = c.post("/v1/register", json=small_pair())
        assert late.status_code == 504
        assert_conforms(doc, "POST", "/v1/register", late)


def test_cors_allows_only_the_configured_origins(strict_server):
    with strict_server.client() as c:
        preflight = {"Access-Control-Request-Method": "POST", "Access-Control-Request-Headers": "content-type"}
        allowed = c.options("/v1/register", headers={"Origin": CORS_ORIGIN, **preflight})
        assert allowed.status_code == 200 and allowed.headers["access-control-allow-origin"] == CORS_ORIGIN
        other = c.options("/v1/register", headers={"Origin": "https://evil.example", **preflight})
        assert "access-control-allow-origin" not in other.headers


def test_the_request_contexts_own_refusals_carry_the_cors_headers(strict_server):
    """A 413 from the Content-Length (every oversized browser upload) and a 400 for two Content-Types were answered
    outside the CORS middleware: a cross-origin page saw "Failed to fetch" instead of the message."""
    url = urlsplit(strict_server.url)
    with socket.create_connection((url.hostname, url.port), timeout=10) as sock:
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nOrigin: "
                     + CORS_ORIGIN.encode() + b"\r\nContent-Length: 100000000000\r\n\r\n")
        head = b""
        while b"\r\n\r\n" not in head:
            head += sock.recv(65536)
    status_line, *lines = head.split(b"\r\n\r\n")[0].decode("latin-1").split("\r\n")
    headers = {name.strip().lower(): value.strip() for name, _, value in (line.partition(":") for line in lines)}
    assert status_line.split()[1] == "413" and headers["access-control-allow-origin"] == CORS_ORIGIN
    with strict_server.client() as c:
        two_types = [("Content-Type", "application/json"), ("Content-Type", "text/plain"), ("Origin", CORS_ORIGIN)]
        response = c.post("/v1/register", content=b"{}", headers=two_types)
    assert response.status_code == 400 and response.headers["access-control-allow-origin"] == CORS_ORIGIN


@pytest.mark.parametrize("route", ["/v1/register", "/v1/register/batch"])
def test_a_flat_list_of_numbers_over_the_point_limit_is_named_by_its_shape(client, route):
    """It got the 413 of a cloud of as many points as numbers (1,200 numbers: 400 points, within the limit)."""
    pair = small_pair()
    pair["source"] = np.asarray(modelnet_pair(1).source[:LIMITED["max_points"]]).ravel().tolist()  # [3 N]
    body, name = (pair, "source") if route == "/v1/register" else ({"pairs": [small_pair(), pair]}, "pairs[1].source")
    assert_error(client.post(route, json=body), 422, f"{name}: a flat list of {3 * LIMITED['max_points']} numbers",
                 f"reshape it to [{LIMITED['max_points']}, 3]")
