"""HTTP semantics real clients and proxies rely on, against the main server: compressed bodies, trailing slashes,
repeated headers and batch errors. The requests use a generated shape (``api_server.synthetic_pair``) and run cheap
options, so the module needs neither the ModelNet40 files nor seconds of work."""

from __future__ import annotations

import gzip
import io
import json
import socket
import time

import httpx
import numpy as np
import pytest
from api_server import assert_error, pair_json, start_subprocess_server, synthetic_pair

CHEAP = {"iterations": 1, "keypoints": 16, "refine": "none"}


def pair(**options) -> dict:
    return pair_json(synthetic_pair(5), **CHEAP, **options)


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def gzipped_multipart() -> tuple[bytes, str]:
    """A multipart upload of the pair, gzipped, and its Content-Type."""
    p = synthetic_pair(5)
    request = httpx.Request("POST", "http://x/", files={"source": ("s.npy", npy(p.source)),
                                                        "target": ("t.npy", npy(p.target))})
    return gzip.compress(request.read()), request.headers["content-type"]


@pytest.mark.parametrize("path", ["/v1/register", "/v1/register/batch", "/v1/register/view", "/v1/register/aligned"])
def test_a_compressed_body_is_a_415_naming_content_encoding_on_every_v1_route(client, path):
    """The error docs promised a 415 for a Content-Encoding; /v1 read the gzip bytes as the body (a 400 "not UTF-8
    text", or a multipart parse error). RFC 7694: the 415 says which coding the server reads."""
    if path.endswith(("view", "aligned")):
        body, content_type = gzipped_multipart()
    else:
        body, content_type = gzip.compress(json.dumps({"pairs": [pair()]} if "batch" in path else pair()).encode()), \
            "application/json"
    response = client.post(path, content=body, headers={"content-type": content_type, "content-encoding": "gzip"})
    assert_error(response, 415, "content-encoding", "gzip", "uncompressed")
    assert response.headers["accept-encoding"] == "identity"
    plain = client.post("/v1/register", json=pair(), headers={"content-encoding": "identity"})
    assert plain.status_code == 200, plain.text


def test_a_coding_on_a_second_content_encoding_line_is_a_415(server):
    """Each header line counts: ``identity`` on the first line and ``gzip`` on the second was read as an uncompressed
    body (a 400 "malformed JSON" for the gzip bytes)."""
    head = (b"POST /v1/register HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n"
            b"Content-Encoding: identity\r\nContent-Encoding: gzip\r\n")
    reply = raw_request(server, head, gzip.compress(json.dumps(pair()).encode()))
    assert reply.startswith(b"HTTP/1.1 415 ") and b"gzip" in reply, reply[:400]


def raw_request(server, head: bytes, body: bytes) -> bytes:
    url = httpx.URL(server.url)
    with socket.create_connection((url.host, url.port), timeout=30) as sock:
        sock.sendall(head + b"Content-Length: %d\r\nConnection: close\r\n\r\n" % len(body) + body)
        reply = b""
        while chunk := sock.recv(65536):
            reply += chunk
    return reply


@pytest.mark.parametrize("types", [(b"application/json", b"text/plain"), (b"text/plain", b"application/json")])
def test_two_different_content_types_are_a_400(server, types):
    """The server read the first and a proxy may read the last: the same bytes meant two things (RFC 9110 5.3)."""
    head = b"POST /v1/register HTTP/1.1\r\nHost: test\r\n" + b"".join(b"Content-Type: %s\r\n" % t for t in types)
    reply = raw_request(server, head, json.dumps(pair()).encode())
    assert reply.startswith(b"HTTP/1.1 400 "), reply[:300]
    assert b"Content-Type" in reply and b"application/json" not in reply.split(b"\r\n\r\n", 1)[1]


def test_the_same_content_type_twice_is_read(server):
    head = b"POST /v1/register HTTP/1.1\r\nHost: test\r\n" + b"Content-Type: application/json\r\n" * 2
    reply = raw_request(server, head, json.dumps(pair()).encode())
    assert reply.startswith(b"HTTP/1.1 200 "), reply[:300]



@pytest.mark.parametrize("tokens", [(b"wrong", b"right"), (b"right", b"wrong")])
def test_two_different_authorization_headers_are_a_400(server, tokens):
    """As two Content-Types: the server read the first and a proxy may have read (or checked) the last."""
    head = (b"POST /v1/register HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n"
            + b"".join(b"Authorization: Bearer %s\r\n" % token for token in tokens))
    reply = raw_request(server, head, json.dumps(pair()).encode())
    assert reply.startswith(b"HTTP/1.1 400 ") and b"Authorization headers that differ" in reply, reply[:300]



def test_one_credential_in_two_spellings_of_its_scheme_is_read(server):
    """The scheme is case-insensitive (RFC 9110 11.1): ``Bearer x`` and ``bearer x`` are one credential, not two."""
    head = (b"POST /v1/register HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n"
            b"Authorization: Bearer same\r\nAuthorization: bearer  same\r\n")
    reply = raw_request(server, head, json.dumps(pair()).encode())
    assert reply.startswith(b"HTTP/1.1 200 "), reply[:300]

@pytest.mark.parametrize("path", ["/v1/register?model=clean&refine=icp", "/v2/models/general/infer?model_version=1"])
def test_query_parameters_on_a_post_route_are_a_400_naming_them(client, path):
    """No POST route reads its query string: ``?model=clean`` registered with the default model, silently."""
    response = client.post(path, json=pair())
    names = path.partition("?")[2].replace("=clean", "").replace("=icp", "").replace("=1", "").replace("&", ", ")
    assert_error(response, 400, "query parameters are not read", f"({names})", "request body")

def test_a_batch_pairs_unknown_model_is_named_by_its_index(client):
    response = client.post("/v1/register/batch", json={"pairs": [pair(), pair(model="nope")]})
    assert_error(response, 404, "pairs[1].model", "unknown model 'nope'")


@pytest.mark.parametrize("path", ["/v1/register/", "/v1/register/batch/", "/v1/models/", "/v2/health/ready/"])
def test_a_trailing_slash_is_a_404_naming_the_route_not_a_redirect(client, path):
    """A 307 made clients that follow it (requests, curl -L) send a POST's body twice, to a Location built from the
    Host header and scheme the server saw (http:// behind a TLS proxy)."""
    method = "POST" if "register" in path else "GET"
    response = client.request(method, path, json=pair() if method == "POST" else None)
    assert "location" not in response.headers
    assert_error(response, 404, f"not found: {method} {path}", f"take no trailing slash: {path.rstrip('/')}")


def test_an_unknown_path_with_a_trailing_slash_gets_no_hint(client):
    response = client.get("/v1/no-such-route/")
    assert "trailing slash" not in assert_error(response, 404, "/v1/no-such-route/")["error"]


def _logged_client(server, request_id: str) -> str:
    """The ``client`` of ``request_id``'s access line, once the server has written it (after its answer)."""
    deadline = time.monotonic() + 5
    while True:
        lines = [line for line in server.log_lines() if line.get("request_id") == request_id]
        if lines or time.monotonic() > deadline:
            assert len(lines) == 1, lines
            return lines[0]["client"]
        time.sleep(0.02)


def test_the_access_log_names_the_forwarded_client_only_behind_a_trusted_proxy(server):
    """DEPLOYMENT.md, "Logs": X-Forwarded-For names the client when the peer is trusted (127.0.0.1 by default, a
    sidecar), and uvicorn's FORWARDED_ALLOW_IPS says which peers are."""
    headers = {"X-Forwarded-For": "203.0.113.7", "X-Request-ID": "forwarded-by-a-sidecar"}
    with server.client() as c:
        assert c.get("/v2/health/live", headers=headers).status_code == 200
    assert _logged_client(server, "forwarded-by-a-sidecar") == "203.0.113.7"
    elsewhere = start_subprocess_server("proxy-elsewhere", FORWARDED_ALLOW_IPS="192.0.2.1")
    try:
        with elsewhere.client() as c:
            assert c.get("/v2/health/live", headers=headers).status_code == 200
        assert _logged_client(elsewhere, "forwarded-by-a-sidecar") == "127.0.0.1"
    finally:
        elsewhere.stop()


def test_head_requests_of_the_page_files_are_200s_named_by_their_route_whenever_the_client_closes():
    """A HEAD answer is whole once its headers are out: a client (an uptime monitor, curl --head) that closes on them
    can cancel the file response it is served as, which must not make it a 499 in the access log and the metrics
    (before, some such requests were)."""
    server = start_subprocess_server("head_requests")
    url = httpx.URL(server.url)
    try:
        for _ in range(20):
            for path in (b"/", b"/page/index.html", b"/page/page.css"):
                with socket.create_connection((url.host, url.port), timeout=30) as sock:
                    sock.sendall(b"HEAD " + path + b" HTTP/1.1\r\nHost: test\r\n\r\n")
                    assert sock.recv(65536).startswith(b"HTTP/1.1 200 ")
        with server.client() as client:  # and answers read whole, on a connection kept alive
            assert all(client.head(path).status_code == 200 for path in ("/", "/page/index.html") * 5)
        deadline = time.monotonic() + 10
        while len(heads := [line for line in server.log_lines() if line.get("method") == "HEAD"]) < 70:
            assert time.monotonic() < deadline, len(heads)
            time.sleep(0.2)
        assert {line["status"] for line in heads} == {200}
        # named by the route GET matched, also where the answer is counted as its last body goes out (before: the
        # page's `/` was sometimes counted under `<unmatched>`)
        assert {line["route"] for line in heads} == {"/", "/page"}
    finally:
        server.stop()


@pytest.mark.parametrize("value", ["items=0-1", "bytes=5-1", "bytes=abc", "bytes=-0", "bytes="])
@pytest.mark.parametrize("path", ["/", "/page/page.js"])
def test_a_range_the_files_cannot_serve_is_ignored(client, path, value):
    """RFC 9110 14.2: a server MUST ignore a range unit it does not understand (and may ignore a malformed range):
    Starlette answered a plain-text 400, where every error is JSON."""
    whole = client.get(path)
    ranged = client.get(path, headers={"Range": value})
    assert ranged.status_code == 200 and ranged.content == whole.content, (ranged.status_code, ranged.text[:100])


def test_a_well_formed_byte_range_of_a_file_is_served(client):
    whole = client.get("/page/page.js").content
    ranged = client.get("/page/page.js", headers={"Range": "bytes=0-9"})
    assert ranged.status_code == 206 and ranged.content == whole[:10]
    assert client.get("/page/page.js", headers={"Range": f"bytes={len(whole) + 10}-"}).status_code == 416



def test_a_query_behind_a_hash_is_read_as_sent(server):
    """A "#" reaches the server only from a client that sends it: the query is taken as sent, not cut as a URL's
    fragment (``?#model=clean`` was answered as if no query had been sent)."""
    head = b"POST /v1/register?#model=clean HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n"
    reply = raw_request(server, head, json.dumps(pair()).encode())
    assert reply.startswith(b"HTTP/1.1 400 ") and b"query parameters are not read" in reply, reply[:300]
