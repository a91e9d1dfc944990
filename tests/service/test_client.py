"""Specification of ``service.client`` against a mock transport (no server; the real-server checks
are in ``test_cli_server.py``)."""

from __future__ import annotations

import email.parser
import email.policy
import io
import json

import httpx
import numpy as np
import pytest

from service.client import MfgnetClient, MfgnetError, pose_from_response

RESPONSE = {
    "rotation": [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
    "translation": [1.0, 2.0, 3.0],
    "transform": [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]],
    "quality": {"inlier_ratio": 0.9, "residual_rms": 0.01, "reliable": True},
    "warnings": [],
}


class Recorder:
    """An httpx mock handler that records requests and answers with a fixed status and JSON body."""

    def __init__(self, status: int = 200, body=None):
        self.status, self.body, self.requests = status, RESPONSE if body is None else body, []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        return httpx.Response(self.status, json=self.body)


def client_for(handler, **kwargs) -> MfgnetClient:
    return MfgnetClient("http://mfgnet.test/", transport=httpx.MockTransport(handler), **kwargs)


def cloud(n: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)


def multipart_parts(request: httpx.Request) -> dict[str, bytes]:
    """``{field name: raw bytes}`` of a multipart/form-data request."""
    head = f"Content-Type: {request.headers['content-type']}\r\n\r\n".encode()
    message = email.parser.BytesParser(policy=email.policy.default).parsebytes(head + request.content)
    return {part.get_param("name", header="content-disposition"): part.get_payload(decode=True)
            for part in message.iter_parts()}


def test_register_posts_json_with_only_the_given_options() -> None:
    recorder = Recorder()
    src, tgt = cloud(seed=1), cloud(seed=2)
    with client_for(recorder) as client:
        response = client.register(src, tgt, model="clean", iterations=3, refine="icp", initial_transform=np.eye(4))
    assert response == RESPONSE
    (request,) = recorder.requests
    assert request.method == "POST" and request.url.path == "/v1/register"
    body = json.loads(request.content)
    assert np.array_equal(np.asarray(body["source"], dtype=np.float32), src)
    assert np.array_equal(np.asarray(body["target"], dtype=np.float32), tgt)
    assert body["model"] == "clean" and body["iterations"] == 3 and body["refine"] == "icp"
    assert body["initial_transform"] == np.eye(4).tolist()
    assert body["return_correspondences"] is True
    assert "keypoints" not in body  # None options are left to the server's defaults


def test_register_accepts_nested_lists() -> None:
    recorder = Recorder()
    client_for(recorder).register(cloud().tolist(), cloud(seed=3).tolist(), return_correspondences=False)
    body = json.loads(recorder.requests[0].content)
    assert len(body["source"]) == 40 and body["return_correspondences"] is False


def test_binary_register_sends_float32_npy_files_and_form_fields() -> None:
    recorder = Recorder()
    src, tgt = cloud(seed=4).astype(np.float64), cloud(seed=5)
    client_for(recorder).register(src, tgt, keypoints=64, initial_transform=np.eye(4), binary=True)
    (request,) = recorder.requests
    assert request.headers["content-type"].startswith("multipart/form-data")
    parts = multipart_parts(request)
    source = np.load(io.BytesIO(parts["source"]), allow_pickle=False)
    assert source.dtype == np.float32 and np.array_equal(source, src.astype(np.float32))
    assert np.array_equal(np.load(io.BytesIO(parts["target"]), allow_pickle=False), tgt)
    assert parts["keypoints"] == b"64"
    assert parts["return_correspondences"] == b"true"
    assert json.loads(parts["initial_transform"]) == np.eye(4).tolist()
    assert "model" not in parts


@pytest.mark.parametrize(("value", "json_value", "form_value"), [(True, True, b"true"), ("auto", "auto", b"auto")])
def test_rotation_search_is_sent_when_asked(value, json_value, form_value) -> None:
    recorder = Recorder()
    client = client_for(recorder)
    client.register(cloud(), cloud(seed=1), rotation_search=value)
    client.register(cloud(), cloud(seed=1), rotation_search=value, binary=True)
    client.register(cloud(), cloud(seed=1))
    json_request, form_request, default_request = recorder.requests
    assert json.loads(json_request.content)["rotation_search"] == json_value
    assert multipart_parts(form_request)["rotation_search"] == form_value
    assert "rotation_search" not in json.loads(default_request.content)  # off: left to the server's default


def test_api_key_is_sent_as_a_bearer_token() -> None:
    recorder = Recorder(body={"models": []})
    client_for(recorder, api_key="s3cret").models()
    assert recorder.requests[0].headers["authorization"] == "Bearer s3cret"


def test_no_api_key_sends_no_auth_headers() -> None:
    recorder = Recorder(body=[])
    client_for(recorder).models()
    assert "authorization" not in recorder.requests[0].headers


@pytest.mark.parametrize("body", [{"models": [{"name": "clean"}]}, [{"name": "clean"}]])
def test_models_returns_the_list(body) -> None:
    recorder = Recorder(body=body)
    assert client_for(recorder).models() == [{"name": "clean"}]
    assert recorder.requests[0].url.path == "/v1/models"


def test_4xx_raises_mfgnet_error_with_the_servers_error_text() -> None:
    client = client_for(Recorder(422, {"error": "source: needs at least 32 points, got 5"}))
    with pytest.raises(MfgnetError) as info:
        client.register(cloud(5), cloud())
    assert info.value.status == 422
    assert info.value.message == "source: needs at least 32 points, got 5"
    assert "422" in str(info.value)


def test_fastapi_detail_is_used_when_there_is_no_error_field() -> None:
    client = client_for(Recorder(404, {"detail": "Not Found"}))
    with pytest.raises(MfgnetError, match="Not Found") as info:
        client.models()
    assert info.value.status == 404


def test_non_json_error_body_is_reported_verbatim() -> None:
    client = client_for(lambda request: httpx.Response(502, text="Bad Gateway from proxy"))
    with pytest.raises(MfgnetError, match="Bad Gateway from proxy") as info:
        client.models()
    assert info.value.status == 502


def test_unreachable_server_raises_mfgnet_error_with_status_0() -> None:
    def refuse(request):
        raise httpx.ConnectError("connection refused", request=request)

    with pytest.raises(MfgnetError, match="cannot reach") as info:
        client_for(refuse).register(cloud(), cloud())
    assert info.value.status == 0


def test_ready_reflects_the_readiness_endpoint() -> None:
    recorder = Recorder(body={"ready": True})
    assert client_for(recorder).ready() is True
    assert recorder.requests[0].url.path == "/v2/health/ready"
    assert client_for(Recorder(503, {"error": "loading"})).ready() is False


def test_ready_is_false_when_the_server_cannot_be_reached() -> None:
    def refuse(request):
        raise httpx.ConnectError("connection refused", request=request)

    assert client_for(refuse).ready() is False


def test_wait_ready_returns_once_ready_and_times_out_otherwise() -> None:
    answers = iter([503, 503, 200])
    client_for(lambda request: httpx.Response(next(answers), json={})).wait_ready(timeout=5, interval=0.01)
    with pytest.raises(TimeoutError, match="not ready"):
        client_for(Recorder(503, {})).wait_ready(timeout=0.05, interval=0.01)


def test_pose_from_response_reads_the_transform() -> None:
    R, t = pose_from_response(RESPONSE)
    assert np.array_equal(R, np.asarray(RESPONSE["rotation"])) and np.array_equal(t, [1.0, 2.0, 3.0])


def test_pose_from_response_falls_back_to_rotation_and_translation() -> None:
    R, t = pose_from_response({"rotation": RESPONSE["rotation"], "translation": [0, 0, 1]})
    assert R.shape == (3, 3) and np.array_equal(t, [0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "bad", [{}, {"transform": [[1, 0], [0, 1]]}, {"rotation": np.eye(3).tolist(), "translation": [1]}]
)
def test_pose_from_response_rejects_missing_or_misshapen_poses(bad) -> None:
    with pytest.raises(ValueError):
        pose_from_response(bad)


def test_context_manager_closes_the_http_client() -> None:
    with client_for(Recorder()) as client:
        pass
    assert client._http.is_closed
