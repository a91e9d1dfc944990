"""Specification of ``service.client`` over real HTTP.

What the client sends is checked through what a real ``mfgnet`` server (a subprocess on 127.0.0.1, started
once for this module with an API key and rotation search off by default) answers: the model and iteration
count it names, the keypoints it matched, the stages it timed, its 401 and 422 messages. Answers the real
server never gives but a client meets in deployment (a proxy's HTML page, a FastAPI ``detail`` body, a server
that never answers, readiness turning from 503 to 200) come from a minimal ``http.server`` in a thread.
More real-server checks of the client: ``test_cli_server.py`` and ``test_client_large_coordinates.py``.
"""

from __future__ import annotations

import json
import re
import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import numpy as np
import pytest
from api_server import Server, free_port, start_subprocess_server, synthetic_pair

from service.client import MfgnetClient, MfgnetError, pose_from_response

API_KEY = "client-test-key"
FAST = {"iterations": 1, "keypoints": 32}  # the smallest request the model takes
EASY = synthetic_pair(0)  # registered right without a rotation search
HARD = synthetic_pair(5, keep=400, max_angle_deg=180)  # turned so far that rotation_search="auto" searches

RESPONSE = {
    "rotation": [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
    "translation": [1.0, 2.0, 3.0],
    "transform": [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]],
}


# -- the real server ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def keyed_server() -> Iterator[Server]:
    """``mfgnet`` serving the bundled ``clean`` model, asking for ``API_KEY``, rotation search off unless asked."""
    server = start_subprocess_server("client", MFGNET_API_KEY=API_KEY, MFGNET_DEFAULT_ROTATION_SEARCH="off")
    yield server
    server.stop()


@pytest.fixture
def mfgnet(keyed_server) -> Iterator[MfgnetClient]:
    with MfgnetClient(keyed_server.url, api_key=API_KEY, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def model_config(keyed_server) -> dict:
    """The served model's manifest config: its default ``iterations`` and ``keypoints``."""
    with MfgnetClient(keyed_server.url) as client:
        (model,) = client.models()
    return model["config"]


# -- a minimal HTTP server for answers mfgnet never gives --------------------------------------------------
Answer = tuple[int, str, bytes]  # status, content type, body


class _Scripted(BaseHTTPRequestHandler):
    """Answers each request with the next of ``server.answers`` (the last one again once they run out): an
    ``Answer``, or a function of the request handler (its ``path`` and ``headers``) returning one."""

    def _answer(self) -> None:
        self.rfile.read(int(self.headers.get("Content-Length") or 0))
        answers = self.server.answers
        answer = answers.pop(0) if len(answers) > 1 else answers[0]
        status, content_type, body = answer(self) if callable(answer) else answer
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_GET(self) -> None:
        self._answer()

    def do_POST(self) -> None:
        self._answer()

    def log_message(self, *args) -> None:  # keep the test output quiet
        pass


def as_json(status: int, body) -> Answer:
    return status, "application/json", json.dumps(body).encode()


def loading(*ready_statuses: int) -> Callable[[BaseHTTPRequestHandler], Answer]:
    """A server loading its model: ``/v2/health/ready`` answers ``ready_statuses`` in turn (the last from then
    on), every other path 200 (liveness among them)."""
    statuses = list(ready_statuses)

    def answer(request: BaseHTTPRequestHandler) -> Answer:
        if request.path != "/v2/health/ready":
            return as_json(200, {"live": True})
        status = statuses.pop(0) if len(statuses) > 1 else statuses[0]
        return as_json(status, {"ready": True} if status == 200 else {"error": "loading"})

    return answer


@contextmanager
def scripted_server(*answers: Answer | Callable[[BaseHTTPRequestHandler], Answer], port: int = 0) -> Iterator[str]:
    """The base URL of an HTTP server on 127.0.0.1 answering ``answers`` in turn (see ``_Scripted``)."""
    server = ThreadingHTTPServer(("127.0.0.1", port), _Scripted)
    server.answers = list(answers)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@contextmanager
def silent_server() -> Iterator[str]:
    """The base URL of a socket on 127.0.0.1 whose connections are accepted (by the kernel) and never answered."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(8)
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"


def same_pose(a: dict, b: dict) -> bool:
    return np.array_equal(np.asarray(a["transform"]), np.asarray(b["transform"]))


# -- what the client sends --------------------------------------------------------------------------------
def test_register_sends_the_given_options_and_returns_the_servers_json(mfgnet, model_config) -> None:
    response = mfgnet.register(EASY.source, EASY.target, model="clean", iterations=3, refine="icp",
                               initial_transform=np.eye(4))
    assert response["model"]["name"] == "clean" and response["iterations"] == 3
    assert "refine" in response["timing_ms"]  # refine="icp" ran
    assert len(response["correspondences"]) == model_config["keypoints"]  # returned by default; keypoints not sent
    R, t = pose_from_response(response)
    assert np.allclose(R, EASY.rotation, atol=1e-2) and np.allclose(t, EASY.translation, atol=1e-2)
    assert "refine" not in mfgnet.register(EASY.source, EASY.target, refine="none", **FAST)["timing_ms"]


@pytest.mark.parametrize("binary", [False, True])
def test_options_left_out_are_the_servers_defaults(mfgnet, model_config, binary) -> None:
    # drop_isolated=None sent as JSON null, or any None as the form text "None", would be the server's 422
    response = mfgnet.register(EASY.source, EASY.target, binary=binary)
    assert response["iterations"] == model_config["iterations"]
    assert len(response["correspondences"]) == model_config["keypoints"]
    assert "iteration_poses" not in response and "search" not in response["timing_ms"]


@pytest.mark.parametrize("binary", [False, True])
def test_initial_transform_reaches_the_server(mfgnet, binary) -> None:
    assert mfgnet.register(EASY.source, EASY.target, initial_transform=np.eye(4), binary=binary, **FAST)
    with pytest.raises(MfgnetError) as info:
        mfgnet.register(EASY.source, EASY.target, initial_transform=np.ones((4, 4)), binary=binary, **FAST)
    assert info.value.status == 422 and "initial_transform must be rigid" in info.value.message


def test_register_sends_json_with_the_clouds_as_given(mfgnet) -> None:
    with pytest.raises(MfgnetError) as info:  # the JSON body's validation names the shape sent
        mfgnet.register(EASY.source[:, :2], EASY.target)
    assert info.value.status == 422 and "source: expected shape [N, 3]" in info.value.message
    assert f"got [{len(EASY.source)}, 2]" in info.value.message
    fine = EASY.source.astype(np.float64) + np.random.default_rng(0).normal(scale=1e-5, size=EASY.source.shape)
    as_float64 = mfgnet.register(fine, EASY.target, **FAST)
    as_float32 = mfgnet.register(fine.astype(np.float32), EASY.target, **FAST)
    assert not same_pose(as_float64, as_float32)  # JSON keeps float64 digits: the server sees the difference


def test_register_accepts_nested_lists(mfgnet) -> None:
    arrays = mfgnet.register(EASY.source, EASY.target, **FAST)
    lists = mfgnet.register(EASY.source.tolist(), EASY.target.tolist(), return_correspondences=False, **FAST)
    assert "correspondences" not in lists and same_pose(lists, arrays)


def test_binary_register_uploads_float32_npy_files_and_form_fields(mfgnet) -> None:
    for bad in ("source", "target"):  # the server names the uploaded file
        clouds = {"source": EASY.source, "target": EASY.target, bad: EASY.source[:40, :2]}
        with pytest.raises(MfgnetError) as info:
            mfgnet.register(**clouds, binary=True)
        assert info.value.status == 422 and f"{bad} ({bad}.npy): expected shape [N, 3]" in info.value.message
    fine = EASY.source.astype(np.float64) + np.random.default_rng(0).normal(scale=1e-5, size=EASY.source.shape)
    binary = mfgnet.register(fine, EASY.target, keypoints=64, initial_transform=np.eye(4), binary=True)
    json_float32 = mfgnet.register(fine.astype(np.float32), EASY.target, keypoints=64, initial_transform=np.eye(4))
    assert same_pose(binary, json_float32)  # the same float32 values arrived
    assert len(binary["correspondences"]) == 64 and binary["model"]["name"] == "clean"  # keypoints sent, model not


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize(("value", "pair"), [(True, EASY), ("auto", HARD)], ids=["true", "auto"])
def test_rotation_search_is_sent_when_asked(mfgnet, binary, value, pair) -> None:
    # the server's default is off: a search ran only if the value arrived
    assert "search" in mfgnet.register(pair.source, pair.target, rotation_search=value, binary=binary,
                                       **FAST)["timing_ms"]


def test_rotation_search_auto_is_not_true_and_none_is_the_servers_default(mfgnet) -> None:
    assert "search" not in mfgnet.register(EASY.source, EASY.target, rotation_search="auto", **FAST)["timing_ms"]
    for binary in (False, True):  # left out: the server's "off", even where "auto" would search
        assert "search" not in mfgnet.register(HARD.source, HARD.target, binary=binary, **FAST)["timing_ms"]


def test_api_key_is_sent_as_a_bearer_token(keyed_server) -> None:
    with MfgnetClient(keyed_server.url, api_key=API_KEY) as client:
        assert client.register(EASY.source, EASY.target, **FAST)["model"]["name"] == "clean"
    with MfgnetClient(keyed_server.url, api_key="not-the-key") as client, pytest.raises(MfgnetError) as info:
        client.register(EASY.source, EASY.target, **FAST)
    assert info.value.status == 401


def test_no_api_key_sends_no_key(keyed_server) -> None:
    with MfgnetClient(keyed_server.url) as client:
        assert [model["name"] for model in client.models()] == ["clean"]  # an open route
        with pytest.raises(MfgnetError) as info:
            client.register(EASY.source, EASY.target, **FAST)
    assert info.value.status == 401 and "missing or invalid API key" in info.value.message


def test_no_api_key_sends_no_authorization_header() -> None:
    """mfgnet ignores a stray ``Authorization`` header; a gateway that refuses credentials it did not issue does not."""

    def refuse_credentials(request: BaseHTTPRequestHandler) -> Answer:
        if "Authorization" in request.headers:
            return as_json(400, {"error": f"unexpected credentials: {request.headers['Authorization']}"})
        return as_json(200, {"models": [{"name": "clean"}]})

    with scripted_server(refuse_credentials) as url, MfgnetClient(url) as client:
        assert client.models() == [{"name": "clean"}]


@pytest.mark.parametrize(("key", "url", "words"), [("s3cret\n", "http://127.0.0.1:9", "api_key must be printable"),
                                                   ("ключ", "http://127.0.0.1:9", "api_key must be printable"),
                                                   ("s3cret", "http://[::1", "is not a URL")])
def test_a_key_or_url_no_request_can_carry_is_a_value_error(key, url, words) -> None:
    """A key read from a file with its line break was an MfgnetError as if the server could not be reached, and a
    non-ASCII key or an unparsable URL a UnicodeEncodeError or httpx's InvalidURL."""
    with pytest.raises(ValueError, match=words):
        MfgnetClient(url, api_key=key)


# -- what the client makes of the answers -----------------------------------------------------------------
def test_4xx_raises_mfgnet_error_with_the_servers_error_text(keyed_server, mfgnet) -> None:
    with pytest.raises(MfgnetError) as info:
        mfgnet.register(EASY.source[:5], EASY.target)
    with keyed_server.client(headers={"Authorization": f"Bearer {API_KEY}"}) as http:
        answer = http.post("/v1/register", json={"source": EASY.source[:5].tolist(), "target": EASY.target.tolist()})
    assert info.value.status == answer.status_code == 422
    assert info.value.message == answer.json()["error"] and "32" in info.value.message
    assert "HTTP 422" in str(info.value)
    request_id = info.value.request_id  # the server's access line of that request carries it
    assert re.fullmatch(r"[0-9a-f]{32}", request_id) and request_id != answer.headers["x-request-id"]


def test_models_returns_a_bare_list_as_it_is() -> None:
    with scripted_server(as_json(200, [{"name": "clean"}])) as url, MfgnetClient(url) as client:
        assert client.models() == [{"name": "clean"}]


def test_fastapi_detail_is_used_when_there_is_no_error_field() -> None:
    with (scripted_server(as_json(404, {"detail": "Not Found"})) as url, MfgnetClient(url) as client,
          pytest.raises(MfgnetError, match="Not Found") as info):
        client.models()
    assert info.value.status == 404 and info.value.message == "Not Found"


def test_non_json_error_body_is_reported_verbatim() -> None:
    page = (502, "text/html", b"<html><body>Bad Gateway from proxy</body></html>\n")
    with scripted_server(page, (502, "text/plain", b"")) as url, MfgnetClient(url) as client:
        with pytest.raises(MfgnetError) as info:
            client.register(EASY.source, EASY.target)
        assert info.value.status == 502 and info.value.message == "<html><body>Bad Gateway from proxy</body></html>"
        with pytest.raises(MfgnetError) as info:  # an empty body: the status's reason
            client.models()
        assert info.value.status == 502 and info.value.message == "Bad Gateway"


def test_non_json_success_body_raises_mfgnet_error() -> None:
    portal = (200, "text/html", b"<html>Please sign in</html>")
    with scripted_server(portal) as url, MfgnetClient(url) as client, pytest.raises(MfgnetError) as info:
        client.models()
    assert info.value.status == 200 and "not JSON" in info.value.message and "Please sign in" in info.value.message


def test_unreachable_server_raises_mfgnet_error_with_status_0() -> None:
    with MfgnetClient(f"http://127.0.0.1:{free_port()}") as client, pytest.raises(MfgnetError) as info:
        client.register(EASY.source, EASY.target)
    assert info.value.status == 0 and "cannot reach" in info.value.message


def test_server_that_never_answers_raises_mfgnet_error_with_status_0() -> None:
    with silent_server() as url, MfgnetClient(url, timeout=0.2) as client:
        with pytest.raises(MfgnetError) as info:
            client.register(EASY.source, EASY.target)
        assert info.value.status == 0 and "no answer" in info.value.message
        assert client.ready() is False


def test_ready_reflects_the_readiness_endpoint(keyed_server) -> None:
    with MfgnetClient(keyed_server.url) as client:
        assert client.ready() is True  # the real server's /v2/health/ready
    with scripted_server(loading(503)) as url, MfgnetClient(url) as client:  # live, not ready
        assert client.ready() is False


def test_ready_is_false_when_the_server_cannot_be_reached() -> None:
    with MfgnetClient(f"http://127.0.0.1:{free_port()}") as client:
        assert client.ready() is False


def test_wait_ready_returns_once_ready_and_times_out_otherwise() -> None:
    with scripted_server(loading(503, 503, 200)) as url, MfgnetClient(url) as client:
        client.wait_ready(timeout=5, interval=0.01)
        assert client.ready() is True
    with (scripted_server(loading(503)) as url, MfgnetClient(url) as client,
          pytest.raises(TimeoutError, match="not ready")):
        client.wait_ready(timeout=0.05, interval=0.01)


def test_a_transport_with_retries_waits_for_a_server_that_starts_late() -> None:
    """``transport`` is for users: here connection retries while a server restarts (httpx waits 0, 0.5, 1 s)."""
    port, started, done = free_port(), threading.Event(), threading.Event()

    def serve_late() -> None:
        with scripted_server(as_json(200, {"models": [{"name": "clean"}]}), port=port):
            started.set()
            done.wait(10)

    late = threading.Timer(0.2, serve_late)  # nobody listens on the port for the client's first try
    late.start()
    try:
        with MfgnetClient(f"http://127.0.0.1:{port}", transport=httpx.HTTPTransport(retries=3)) as client:
            assert client.models() == [{"name": "clean"}]
        assert started.is_set()
    finally:
        done.set()
        late.join(10)


# -- responses and lifecycle ----------------------------------------------------------------------------
def test_pose_from_response_reads_the_transform(mfgnet) -> None:
    R, t = pose_from_response(RESPONSE)
    assert np.array_equal(R, np.asarray(RESPONSE["rotation"])) and np.array_equal(t, [1.0, 2.0, 3.0])
    response = mfgnet.register(EASY.source, EASY.target, **FAST)
    R, t = pose_from_response(response)
    assert np.allclose(R, response["rotation"], atol=1e-9) and np.allclose(t, response["translation"], atol=1e-9)


def test_pose_from_response_falls_back_to_rotation_and_translation() -> None:
    R, t = pose_from_response({"rotation": RESPONSE["rotation"], "translation": [0, 0, 1]})
    assert R.shape == (3, 3) and np.array_equal(t, [0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "bad", [{}, {"transform": [[1, 0], [0, 1]]}, {"rotation": np.eye(3).tolist(), "translation": [1]}]
)
def test_pose_from_response_rejects_missing_or_misshapen_poses(bad) -> None:
    with pytest.raises(ValueError):
        pose_from_response(bad)


def test_context_manager_closes_the_http_client(keyed_server) -> None:
    with MfgnetClient(keyed_server.url) as client:
        assert client.ready()
    assert client._http.is_closed


def test_an_array_beside_a_file_path_keeps_its_float64_digits(mfgnet, tmp_path) -> None:
    """Without ``binary``, arrays travel with their float64 digits, as in JSON, also beside a file path (uploaded as
    it is): the array's pose is the one two float64 arrays give, not the one of its float32 rounding."""
    target = tmp_path / "target.npy"
    np.save(target, EASY.target.astype(np.float64))
    fine = EASY.source.astype(np.float64) + np.random.default_rng(0).normal(scale=1e-5, size=EASY.source.shape)
    beside_a_path = mfgnet.register(fine, str(target), **FAST)
    as_float64 = mfgnet.register(fine, EASY.target.astype(np.float64), **FAST)
    as_float32 = mfgnet.register(fine.astype(np.float32), EASY.target.astype(np.float64), **FAST)
    assert same_pose(beside_a_path, as_float64) and not same_pose(beside_a_path, as_float32)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("kind", [bool, complex], ids=["bool", "complex"])
def test_clouds_that_are_not_numbers_are_the_servers_422(mfgnet, binary, kind) -> None:
    """Booleans (0 and 1 as coordinates) and complex numbers (their imaginary part dropped) are not sent as cast
    coordinates: the server refuses them, naming the source."""
    with pytest.raises(MfgnetError) as info:
        mfgnet.register(EASY.source.astype(kind), EASY.target, binary=binary, **FAST)
    assert info.value.status == 422 and "source" in info.value.message, info.value.message
