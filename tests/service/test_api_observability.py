"""Specification of what an operator reads: the access log lines and the ``/metrics`` series of the main real server
(``api_server.py``), as a log shipper and a Prometheus scrape see them."""

from __future__ import annotations

import json
import random
import re
import socket
import string
import time
import uuid
from urllib.parse import urlsplit

import pytest
from api_server import pair_json, synthetic_pair


def access_line(server, request_id: str) -> tuple[dict, str]:
    """The one access line of ``request_id`` (parsed and as written), once the server has written it."""
    deadline = time.monotonic() + 5
    while True:
        raw = [line for line in server.log_path.read_text().splitlines() if f'"request_id": "{request_id}"' in line]
        access = [line for line in raw if json.loads(line)["logger"] == "mfgnet.access"]
        if access or time.monotonic() > deadline:
            assert len(access) == 1, raw
            return json.loads(access[0]), access[0]
        time.sleep(0.02)


def series(text: str) -> set[str]:
    return {line.rsplit(" ", 1)[0] for line in text.splitlines() if line and not line.startswith("#")}


def count(text: str, **labels: str) -> float:
    """``mfgnet_http_requests_total`` of exactly these labels (0 when absent)."""
    wanted = "mfgnet_http_requests_total{" + ",".join(f'{k}="{v}"' for k, v in sorted(labels.items())) + "}"
    for line in text.splitlines():
        if line.startswith(wanted + " "):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def test_access_line_of_a_refused_request_says_why_without_a_traceback(server, client):
    request_id = "why-" + uuid.uuid4().hex
    body = pair_json(synthetic_pair(0), iterations=1)
    body["source"][0] = body["source"][0][:2]
    response = client.post("/v1/register", json=body, headers={"X-Request-ID": request_id})
    assert response.status_code == 422 and response.headers["x-request-id"] == request_id
    line, _ = access_line(server, request_id)
    assert line["level"] == "info" and line["status"] == 422 and "exc" not in line
    assert line["error"] == response.json()["error"]  # e.g. "invalid request: source[0]: ..."
    assert "source[0]" in line["error"]

    request_id = "why-" + uuid.uuid4().hex
    assert client.get("/no-such-route", headers={"X-Request-ID": request_id}).status_code == 404
    assert access_line(server, request_id)[0]["error"] == "not found: GET /no-such-route"

    request_id = "ok-" + uuid.uuid4().hex
    assert client.get("/v1/models", headers={"X-Request-ID": request_id}).status_code == 200
    assert "error" not in access_line(server, request_id)[0]


def test_access_line_of_a_client_that_went_away_says_so(server):
    request_id = "gone-" + uuid.uuid4().hex
    url = urlsplit(server.url)
    with socket.create_connection((url.hostname, url.port)) as sock:
        sock.sendall(f"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     f"Content-Length: 100000\r\nX-Request-ID: {request_id}\r\n\r\n".encode() + b'{"source": [')
        time.sleep(0.2)
    line, _ = access_line(server, request_id)
    assert line["status"] == 499 and "client closed the connection" in line["error"]


def test_access_line_of_a_huge_path_stays_short(server, client):
    """A request line of up to 16 KiB is read (h11's limit on the request line and headers): each was written whole
    into the access line (and the error)."""
    request_id = "long-" + uuid.uuid4().hex
    response = client.get("/" + "a" * 15_000, headers={"X-Request-ID": request_id})
    assert response.status_code == 404 and len(response.content) < 1_000  # the 404 named the whole path
    assert response.json()["error"].endswith("...")
    line, raw = access_line(server, request_id)
    assert line["path"].startswith("/aaaa") and line["path"].endswith("...")
    assert len(raw) < 1_000
    assert line["error"].startswith("not found: GET /aaaa")  # the 404's message, read back whole
    for path in ("/v2/models/" + "m" * 15_000, "/v2/models/" + "m" * 15_000 + "/ready"):  # a model name that long
        response = client.get(path)
        assert response.status_code == 404 and len(response.content) < 1_000, (path[:40], len(response.content))


def request_count_delta(before: str, after: str):
    """``delta(**labels)``: how much ``mfgnet_http_requests_total`` of those labels grew from scrape ``before`` to
    scrape ``after``."""
    return lambda **labels: count(after, **labels) - count(before, **labels)


def test_metrics_name_the_api_description_and_static_files_by_their_route(client):
    """Starlette's plain routes and mounts set no FastAPI route: they were counted with the unknown paths."""
    before = client.get("/metrics").text
    assert client.get("/openapi.json").status_code == 200
    assert client.get("/page/page.js").status_code == 200
    assert client.get("/page/no-such-file.js").status_code == 404
    delta = request_count_delta(before, client.get("/metrics").text)

    assert delta(route="/openapi.json", method="GET", status="200") == 1
    assert delta(route="/page", method="GET", status="200") == 1
    assert delta(route="/page", method="GET", status="404") == 1
    assert delta(route="<unmatched>", method="GET", status="200") == 0
    assert delta(route="<unmatched>", method="GET", status="404") == 0


def test_a_request_is_counted_before_its_client_can_scrape_again(client):
    """The count was taken after the last bytes had gone: a scrape sent right after an answer missed it about two
    times in three (a static file on a kept-alive connection)."""
    for _ in range(30):
        before = client.get("/metrics").text
        assert client.get("/page/page.js").status_code == 200
        assert request_count_delta(before, client.get("/metrics").text)(route="/page", method="GET", status="200") == 1


def test_head_probes_and_requests_refused_before_routing_are_named_by_their_route(server, client):
    """HEAD requests (answered as GET on a copy of the request) and a 413 from ``Content-Length`` (before routing)
    were counted and logged under ``<unmatched>``, which the docs keep for paths no route serves."""
    before = client.get("/metrics").text
    assert client.head("/v2/health/live").status_code == 200
    assert client.head("/v1/models").status_code == 200
    request_id = "huge-" + uuid.uuid4().hex
    url = urlsplit(server.url)
    with socket.create_connection((url.hostname, url.port)) as sock:
        sock.sendall(f"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     f"Content-Length: 1000000000\r\nX-Request-ID: {request_id}\r\n\r\n".encode())
        assert sock.recv(4096).startswith(b"HTTP/1.1 413")
    delta = request_count_delta(before, client.get("/metrics").text)

    assert delta(route="/v2/health/live", method="HEAD", status="200") == 1
    assert delta(route="/v1/models", method="HEAD", status="200") == 1
    assert delta(route="/v1/register", method="POST", status="413") == 1
    assert delta(route="<unmatched>", method="HEAD", status="200") == 0
    assert delta(route="<unmatched>", method="POST", status="413") == 0
    line, _ = access_line(server, request_id)
    assert line["route"] == "/v1/register" and line["status"] == 413



def test_a_head_request_refused_logs_what_its_get_would_say(server, client):
    """A HEAD answer has no body, but its access line names the error as the GET's does: it logged none."""
    request_ids = {method: f"{method.lower()}-{uuid.uuid4().hex}" for method in ("GET", "HEAD")}
    for method, request_id in request_ids.items():
        answer = client.request(method, "/v2/models/no-such-model", headers={"X-Request-ID": request_id})
        assert answer.status_code == 404
    get_line, head_line = (access_line(server, request_id)[0] for request_id in request_ids.values())
    assert "no-such-model" in get_line["error"] and head_line["error"] == get_line["error"], (get_line, head_line)

def test_a_thousand_unknown_paths_add_no_series(client):
    rng = random.Random(0)
    for method in ("GET", "POST", "PUT", "DELETE"):  # each method's <unmatched> 404 series exists first
        client.request(method, "/warm-up")
    client.get("/metrics")  # and the scrape's own
    before = series(client.get("/metrics").text)
    for i in range(1000):
        path = "/" + "".join(rng.choices(string.ascii_letters + string.digits, k=12)) + f"/{i}?token=secret{i}"
        assert client.request(rng.choice(["GET", "POST", "PUT", "DELETE"]), path).status_code == 404
    text = client.get("/metrics").text
    assert series(text) == before
    assert "secret" not in text


def test_metrics_export_no_created_series(client):
    """prometheus_client's ``_created`` gauges doubled the counters' series and were in no table."""
    text = client.get("/metrics").text
    assert not re.search(r"^mfgnet_\w+_created", text, flags=re.MULTILINE)


def test_a_forwarded_client_address_is_logged_cut_short(server, client):
    """uvicorn takes the client's address from a trusted proxy's ``X-Forwarded-For`` as it is: 5,000 characters were
    logged whole, where every other field of the line is cut to 256."""
    request_id = "forwarded-" + uuid.uuid4().hex
    client.get("/v2/health/live", headers={"X-Forwarded-For": "a" * 5000, "X-Request-ID": request_id})
    line, _ = access_line(server, request_id)
    assert line["client"] == "a" * 256 + "...", len(line["client"])



@pytest.mark.parametrize(("path", "words"), [("/v1/register", "method HEAD not allowed on /v1/register"),
                                             ("/page/no-such-file.js", "not found: HEAD /page/no-such-file.js")])
def test_a_head_requests_refusal_names_head(server, client, path, words):
    """HEAD is served as its GET: the 405's and 404's messages named GET."""
    request_id = "head-" + uuid.uuid4().hex
    assert client.head(path, headers={"X-Request-ID": request_id}).status_code in (404, 405)
    line, _ = access_line(server, request_id)
    assert line["method"] == "HEAD" and line["error"].startswith(words), line
