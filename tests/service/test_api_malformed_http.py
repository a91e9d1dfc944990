"""Requests h11 cannot parse get a JSON 4xx naming the problem from the service's protocol (``http_protocol.py``), as
every other bad request does: the status h11 suggests (431 for headers too large), the hardening headers,
``connection: close`` and an access line; no 5xx and no traceback. uvicorn's own answer was a plain-text
``400 Invalid HTTP request received.`` whatever the problem, and a malformed rest of a body already answered raised in
the protocol (an asyncio "Fatal error" traceback in the log).

Real sockets against a real server process (``run_server``, the production protocol).
"""

from __future__ import annotations

import json
import socket
import time
from urllib.parse import urlsplit

import pytest
from api_server import main_server, wait_for

from service.api.security_headers import CSP, HEADERS, NOTHING_ALLOWED

REGISTER = b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
SECRET = "s3cret-key"  # in a header line h11 refuses: neither answered nor logged
CASES = {  # name: (bytes sent (or parts, 0.1 s apart), status, words of the error, whether the request reached the app)
    "headers too large": (b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 1_000_000 + b"\r\n\r\n",
                          431, ("headers", "16384 bytes"), False),
    "headers too large in one read": (  # h11 checks the limit only while the headers are incomplete
        b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 20_000 + b"\r\n\r\n", 431,
        ("headers", "16384 bytes"), False),
    "bad request line": (b"GARBAGE\r\n\r\n", 400, ("invalid HTTP request", "illegal request line"), False),
    "invalid header name": (b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nBad Header: y\r\n\r\n", 400,
                            ("invalid HTTP request", "illegal header line"), False),
    "NUL in a header": (b"GET /v1/models HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + SECRET.encode()
                        + b"\x00\r\n\r\n", 400, ("illegal header line",), False),
    "Content-Length not a number": (REGISTER + b"Content-Length: abc\r\n\r\n{}", 400, ("Content-Length",), False),
    "transfer coding not chunked": (REGISTER + b"Transfer-Encoding: gzip\r\n\r\n", 400, ("chunked",), False),
    "bad chunked encoding": (REGISTER + b"Transfer-Encoding: chunked\r\n\r\nzz\r\nabc\r\n", 400,
                             ("invalid HTTP request", "illegal chunk header"), True),
    "bad chunk while the app reads": ([REGISTER + b"Transfer-Encoding: chunked\r\n\r\n3\r\n{\"s\r\n", b"zz\r\n"],
                                      400, ("invalid HTTP request", "illegal chunk header"), True),
}


def connect() -> socket.socket:
    url = urlsplit(main_server().url)
    return socket.create_connection((url.hostname, url.port), timeout=10)


def until_closed(sock: socket.socket) -> bytes:
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    return data


def parse(reply: bytes) -> tuple[int, dict[str, str], bytes]:
    head, _, body = reply.partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in lines:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    return int(status_line.split()[1]), headers, body


def access_line(request_id: str) -> dict:
    found = []
    wait_for(lambda: bool(found.extend(line for line in main_server().log_lines()
                                       if line.get("request_id") == request_id) or found), 5, "the access line")
    return found[0]


@pytest.mark.parametrize("name", list(CASES))
def test_a_malformed_request_gets_a_json_4xx_naming_it(name):
    sent, status, words, reached_app = CASES[name]
    with connect() as sock:
        for part in [sent] if isinstance(sent, bytes) else sent:
            sock.sendall(part)  # 1 MB of headers: read (and dropped) after the answer, so it is not reset away
            time.sleep(0.1)
        reply = until_closed(sock)  # the server shuts its side after the answer
    got, headers, body = parse(reply)
    assert got == status, reply[:300]
    assert headers["content-type"] == "application/json" and int(headers["content-length"]) == len(body)
    assert headers["connection"] == "close"
    for key, value in (*HEADERS, (CSP, NOTHING_ALLOWED.encode())):
        assert headers[key.decode()] == value.decode(), key
    error = json.loads(body)["error"]
    for word in words:
        assert word.lower() in error.lower(), error
    assert not {"GARBAGE", "Bad Header", "zz", SECRET} & set(error.split()), error  # the request's bytes not quoted
    line = access_line(headers["x-request-id"])
    assert line["status"] == status and line["error"] == error and line["client"] == "127.0.0.1"
    assert SECRET not in main_server().log_path.read_text()
    if reached_app:  # the request context's line: its method and route, one line
        assert (line["method"], line["route"]) == ("POST", "/v1/register")


def test_a_malformed_rest_of_a_body_already_answered_closes_the_connection_quietly():
    with connect() as sock:
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: text/plain\r\n"
                     b"Transfer-Encoding: chunked\r\n\r\n")
        reply = b""
        while b"}" not in reply:  # the 415, before the body is read
            reply += sock.recv(65536)
        assert reply.startswith(b"HTTP/1.1 415 "), reply[:200]
        started = time.monotonic()
        sock.sendall(b"zz\r\nabc\r\n")
        assert until_closed(sock) == b""
        assert time.monotonic() - started < 2
    time.sleep(0.2)  # the server's log written
    assert not [line for line in main_server().log_lines() if "Fatal error" in line.get("msg", "")]


def test_a_well_formed_request_after_a_malformed_one_is_served():
    with connect() as sock:
        sock.sendall(b"GARBAGE\r\n\r\n")
        assert until_closed(sock).startswith(b"HTTP/1.1 400 ")
    with connect() as sock:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert until_closed(sock).startswith(b"HTTP/1.1 200 ")


def test_headers_within_the_limit_sent_whole_with_a_long_body_reach_the_app():
    body = b'{"x": [' + b"0," * 50_000 + b"0]}"
    with connect() as sock:
        sock.sendall(REGISTER + b"X-Big: " + b"a" * 16_000 + b"\r\nConnection: close\r\nContent-Length: "
                     + str(len(body)).encode() + b"\r\n\r\n" + body)
        status, _, reply = parse(until_closed(sock))
    assert status == 422 and b"source" in reply, reply[:300]  # the body read and validated: not the headers' 431


def test_a_request_with_both_content_length_and_transfer_encoding_is_refused_and_its_connection_closed():
    """RFC 9112 6.1: a proxy in front may frame the body by the length where h11 frames it by the chunks (request
    smuggling); the server MUST close the connection after answering. The pipelined GET is not answered."""
    body = b'{"source": [], "target": []}'
    with connect() as sock:
        sock.sendall(REGISTER + b"Content-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n" + b"%x\r\n" % len(body)
                     + body + b"\r\n0\r\n\r\nGET /v2/health/live HTTP/1.1\r\nHost: x\r\n\r\n")
        reply = until_closed(sock)
    status, headers, rest = parse(reply)
    assert status == 400 and headers["connection"] == "close", reply[:300]
    assert "Transfer-Encoding" in json.loads(rest)["error"]
    assert reply.count(b"HTTP/1.1 ") == 1


@pytest.mark.parametrize("upgrade", [b"websocket", b"h2c"])
def test_an_upgrade_request_is_served_as_the_http_request_it_also_is(upgrade):
    """The service has no WebSocket route: uvicorn handed a WebSocket upgrade to its WebSocket protocol, which answered
    a bare 403 (no JSON, hardening headers or access line), and logged a warning per other upgrade (h2c)."""
    with connect() as sock:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: %s\r\n"
                     b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                     b"X-Request-ID: upgrade-%s\r\nConnection: close\r\n\r\n" % (upgrade, upgrade))
        status, headers, body = parse(until_closed(sock))
    assert status == 200 and headers["x-content-type-options"] == "nosniff" and json.loads(body), (status, headers)
    assert access_line(f"upgrade-{upgrade.decode()}")["status"] == 200


def test_an_absolute_form_target_is_served_as_its_path():
    """RFC 9112 3.2.2: a server MUST accept ``GET http://host/path`` (as clients send it to a proxy); it was a 404
    for ``/http://host/path``."""
    with connect() as sock:
        sock.sendall(b"GET http://127.0.0.1/v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        status, _, body = parse(until_closed(sock))
    assert status == 200 and json.loads(body), (status, body)



def test_options_asterisk_is_answered_for_the_server():
    """RFC 9110 9.3.7: ``OPTIONS *`` asks about the server (HAProxy's ``option httpchk OPTIONS *`` health check); it
    was a 404."""
    with connect() as sock:
        sock.sendall(b"OPTIONS * HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Request-ID: options-asterisk\r\n"
                     b"Connection: close\r\n\r\n")
        status, headers, body = parse(until_closed(sock))
    assert status == 200 and body == b"", (status, body)
    assert {"GET", "HEAD", "POST"} <= {m.strip() for m in headers["allow"].split(",")}, headers
    assert headers["x-content-type-options"] == "nosniff"
    line = access_line("options-asterisk")
    assert (line["route"], line["status"]) == ("*", 200), line
    with connect() as sock:  # a body over the limit is refused before the middleware: still named by its route
        sock.sendall(b"OPTIONS * HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Request-ID: options-asterisk-413\r\n"
                     b"Content-Length: 999999999999\r\nConnection: close\r\n\r\n")
        status, _, _ = parse(until_closed(sock))
    line = access_line("options-asterisk-413")
    assert (status, line["route"], line["status"]) == (413, "*", 413), (status, line)
    with connect() as sock:  # another method on * is no request about the server: a 404 of no route
        sock.sendall(b"GET * HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Request-ID: get-asterisk\r\nConnection: close\r\n\r\n")
        status, _, _ = parse(until_closed(sock))
    line = access_line("get-asterisk")
    assert (status, line["route"]) == (404, "<unmatched>"), (status, line)


def test_a_percent_encoded_scheme_is_no_absolute_form_target():
    """Matched on the target as sent: ``http%3A//host/...`` decoded looked like one and was served."""
    with connect() as sock:
        sock.sendall(b"GET http%3A//127.0.0.1/v2/health/live HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        status, _, _ = parse(until_closed(sock))
    assert status == 404



def test_a_404_names_the_path_the_access_line_names():
    """The message took the URL's path, which percent-encodes what the target sent as it is (``#`` as ``%23``)."""
    with connect() as sock:
        sock.sendall(b"GET /v2/health/live#frag HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        status, _, body = parse(until_closed(sock))
    assert status == 404 and json.loads(body)["error"].startswith("not found: GET /v2/health/live#frag"), body
