"""Specification of the operational routes: OIP v2 health and metadata, ``/v1/models``, ``/metrics``,
the OpenAPI document, request ids and the JSON request log."""

from __future__ import annotations

import re
import uuid

import numpy as np
from api_server import MODEL, modelnet_pair, pair_json
from shapes import ellipsoid_surface


def test_readiness_is_503_until_models_are_warm_then_200(server, client):
    first = server.first_ready  # asked right after the freshly started process answered liveness
    assert first.status_code == 503
    assert first.headers["retry-after"].isdigit()
    body = first.json()
    assert "not ready" in body["error"] and body["ready"] is False
    assert body["models"] == {MODEL: "loading"}
    ready = client.get("/v2/health/ready")
    assert ready.status_code == 200
    assert ready.json() == {"ready": True, "models": {MODEL: "ready"}}


def test_liveness_and_server_metadata(client):
    assert client.get("/v2/health/live").json() == {"live": True}
    meta = client.get("/v2").json()
    assert meta["name"] == "mfgnet" and meta["version"] and isinstance(meta["extensions"], list)


def test_head_answers_as_get_without_a_body_on_every_get_route(client):
    """Load balancers and uptime checkers probe with HEAD; a GET route answered it 405."""
    for path in ("/v2/health/live", "/v2/health/ready", f"/v2/models/{MODEL}/ready", "/v1/models", "/metrics"):
        head = client.head(path)
        assert head.status_code == 200, (path, head.status_code)
        assert head.content == b"" and int(head.headers["content-length"]) > 0, path
        assert head.headers["content-type"] == client.get(path).headers["content-type"], path
    assert client.head("/v2/models/nope/ready").status_code == 404
    assert client.head("/v1/register").status_code == 405  # a POST route stays POST only


def test_model_metadata_follows_the_inference_protocol(client):
    meta = client.get(f"/v2/models/{MODEL}").json()
    assert meta["name"] == MODEL and meta["versions"] and meta["platform"]
    assert {t["name"]: (t["datatype"], t["shape"]) for t in meta["inputs"]} == {
        "SOURCE": ("FP32", [-1, 3]),
        "TARGET": ("FP32", [-1, 3]),
        "INITIAL_TRANSFORM": ("FP32", [4, 4]),  # optional
    }
    assert {t["name"]: (t["datatype"], t["shape"]) for t in meta["outputs"]} == {
        "TRANSFORM": ("FP32", [4, 4]),
        "SOURCE_INDEX": ("INT64", [-1]),
        "TARGET_INDEX": ("INT64", [-1]),
        "CREDIBILITY": ("FP32", [-1]),
    }
    assert client.get(f"/v2/models/{MODEL}/ready").json() == {"name": MODEL, "ready": True}


def test_models_list_shows_manifest_and_load_status(client):
    body = client.get("/v1/models").json()
    assert body["default_model"] == MODEL
    (model,) = body["models"]
    assert model["name"] == MODEL and model["status"] == "ready" and model["default"] is True
    assert re.fullmatch(r"[0-9a-f]{64}", model["sha256"])
    assert model["config"]["keypoints"] == 128 and model["version"]
    assert isinstance(model["accuracy"], dict) and model["load_seconds"] > 0
    assert "directory" not in model and "/" not in str(model.get("error"))


def metric(text: str, name: str, **labels: str) -> float:
    """The value of the sample ``name{labels}`` in a Prometheus text page (0 if absent)."""
    for line in text.splitlines():
        if line.startswith(name + "{") or line.startswith(name + " "):
            sample_labels = dict(re.findall(r'(\w+)="([^"]*)"', line.rsplit(" ", 1)[0]))  # values may hold spaces
            if all(sample_labels.get(k) == v for k, v in labels.items()):
                return float(line.rsplit(" ", 1)[1])
    return 0.0


def test_metrics_count_requests_and_time_pipeline_stages(client):
    before = client.get("/metrics").text
    for _ in range(3):
        client.get("/v2/health/live")
    assert client.post("/v1/register", json=pair_json(modelnet_pair(1), iterations=1)).status_code == 200
    client.get("/v2/models/nope")
    after = client.get("/metrics")
    assert after.headers["content-type"].startswith("text/plain")
    text = after.text

    def delta(name, **labels):
        return metric(text, name, **labels) - metric(before, name, **labels)

    assert delta("mfgnet_http_requests_total", route="/v2/health/live", method="GET", status="200") == 3
    assert delta("mfgnet_http_requests_total", route="/v1/register", method="POST", status="200") == 1
    assert delta("mfgnet_http_requests_total", route="/v2/models/{name}", method="GET", status="404") == 1
    assert delta("mfgnet_http_request_duration_seconds_count", route="/v1/register") == 1
    for stage in ("preprocess", "encoder", "iterations", "svd", "total", "queue"):
        assert delta("mfgnet_pipeline_stage_seconds_count", model=MODEL, stage=stage) == 1, stage
    assert sum(delta("mfgnet_registration_results_total", model=MODEL, reliable=r) for r in ("true", "false")) == 1
    assert metric(text, "mfgnet_model_load_seconds", model=MODEL) > 0
    assert metric(text, "mfgnet_model_ready", model=MODEL) == 1
    assert metric(text, "mfgnet_http_requests_in_flight") >= 1  # this very request
    assert 'status="500"' not in text


def test_metrics_count_made_up_methods_as_one(client):
    """Each method a client makes up was a new labelled series: /metrics grew without bound."""
    before = client.get("/metrics").text
    for _ in range(5):
        client.request(f"MADEUP{uuid.uuid4().hex[:8].upper()}", "/v1/models")
    text = client.get("/metrics").text
    assert "MADEUP" not in text
    assert metric(text, "mfgnet_http_requests_total", route="/v1/models", method="other", status="405") - metric(
        before, "mfgnet_http_requests_total", route="/v1/models", method="other", status="405") == 5


def test_metrics_count_unreliable_results_by_warning_kind(client):
    """A spheroid's turn about its axis is free: one unreliable result, one 'weakly constrained' warning."""
    before = client.get("/metrics").text
    source = ellipsoid_surface(np.random.default_rng(0), 800, axes=(0.6, 0.6, 1.0), bump=0.0)
    target = ellipsoid_surface(np.random.default_rng(1), 800, axes=(0.6, 0.6, 1.0), bump=0.0)
    body = client.post("/v1/register", json={"source": source.tolist(), "target": target.tolist()}).json()
    assert body["quality"]["reliable"] is False
    after = client.get("/metrics").text
    model = body["model"]["name"]  # the server's default model
    kinds = {w.split(":")[0] for w in body["warnings"]}
    assert "weakly constrained" in kinds
    for kind in kinds:
        assert metric(after, "mfgnet_registration_warnings_total", model=model, kind=kind) - metric(
            before, "mfgnet_registration_warnings_total", model=model, kind=kind) == 1, kind
    assert metric(after, "mfgnet_registration_results_total", model=model, reliable="false") - metric(
        before, "mfgnet_registration_results_total", model=model, reliable="false") == 1


def test_openapi_declares_both_content_types_and_error_responses(client):
    doc = client.get("/openapi.json").json()
    register = doc["paths"]["/v1/register"]["post"]
    assert set(register["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    assert {"400", "404", "413", "415", "422", "503", "504"} <= set(register["responses"])
    assert register["responses"]["422"]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorResponse")
    schemas = doc["components"]["schemas"]
    assert {"RegisterRequest", "RegisterResponse", "BatchRequest", "InferRequest", "ErrorResponse"} <= set(schemas)
    assert schemas["RegisterRequest"]["examples"]
    infer = doc["paths"]["/v2/models/{name}/infer"]["post"]
    assert {"400", "404", "413", "415", "422", "503", "504"} <= set(infer["responses"])


def test_request_id_is_echoed_or_generated(client):
    given = "req-" + uuid.uuid4().hex
    assert client.get("/v2/health/live", headers={"X-Request-ID": given}).headers["x-request-id"] == given
    generated = client.get("/v2/health/live").headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", generated)
    replaced = client.get("/nope", headers={"X-Request-ID": "bad id\twith spaces"}).headers["x-request-id"]
    assert re.fullmatch(r"[0-9a-f]{32}", replaced)  # unsafe ids are not echoed


def test_one_json_log_line_per_request_without_point_data(server, client):
    request_id = "log-" + uuid.uuid4().hex
    pair = modelnet_pair(2)
    body = pair_json(pair, iterations=1)
    assert client.post("/v1/register", json=body, headers={"X-Request-ID": request_id}).status_code == 200
    client.get("/v2/health/live")  # flushes nothing, but gives the log a moment
    lines = [entry for entry in server.log_lines() if entry.get("request_id") == request_id]
    assert len(lines) == 1
    (line,) = lines
    assert line["route"] == "/v1/register" and line["status"] == 200 and line["ms"] > 0
    assert line["logger"] == "mfgnet.access" and line["method"] == "POST"
    log_text = server.log_path.read_text()
    assert repr(float(pair.source[0, 0])) not in log_text and str(body["source"][0]) not in log_text


def test_unknown_warning_kinds_are_counted_as_other():
    """The warning label set is fixed: no request can add a label value."""
    from prometheus_client import generate_latest

    from service.api.metrics import Metrics

    metrics = Metrics()
    metrics.observe_quality("m", True, ["weakly constrained: a turn ...", "source coplanar: ...", "made up 3: x", "x",
                                        "loose fit: ...", "target few distinct points: ..."])
    text = generate_latest(metrics.registry).decode()
    assert metric(text, "mfgnet_registration_results_total", model="m", reliable="true") == 1
    for kind, count in (("weakly constrained", 1), ("source coplanar", 1), ("other", 2), ("loose fit", 1),
                        ("target few distinct points", 1)):
        assert metric(text, "mfgnet_registration_warnings_total", model="m", kind=kind) == count, kind
