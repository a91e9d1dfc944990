"""Hostile clients against a real uvicorn server: request bodies that made 500s, browser hardening headers on every
response (and a real Chromium refusing to frame the page), and connections that send their headers slowly or not
at all (slowloris).

Covered elsewhere and not repeated here: the API key, CORS, request ids and logs (``test_reliability_security.py``,
``test_api_limits.py``), slow bodies (``test_reliability_faults.py``), oversized bodies and counts
(``test_api_limits.py``, ``test_api_large_json.py``), malformed JSON on the /v1 routes (``test_reliability_fuzz.py``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import threading
import time
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

import pytest
from api_server import MODEL, assert_error, main_server, start_subprocess_server

HEADER_TIMEOUT_S = 1.0  # the slow-headers server's
KEEP_ALIVE_S = 3


def infer_body(**top) -> dict:
    cloud = [[i * 0.1, (i * 7 % 11) * 0.1, (i * 5 % 13) * 0.1] for i in range(64)]
    inputs = [{"name": name, "shape": [64, 3], "datatype": "FP32", "data": cloud} for name in ("SOURCE", "TARGET")]
    return {"inputs": inputs, "parameters": {"iterations": 1, "refine": "none"}, **top}


# -- bodies that were 500s ---------------------------------------------------------------------------
@pytest.mark.parametrize("content_type", ["application/json", None])
def test_an_infer_id_with_a_lone_surrogate_is_a_422_not_a_500(content_type):
    """``"id": "\\ud800"`` is valid JSON whose string UTF-8 cannot write: the echoed id made the response a 500."""
    body = json.dumps(infer_body(id="\ud800"))  # ensure_ascii: the escape as a client sends it
    assert "\\ud800" in body
    headers = {"content-type": content_type} if content_type else {}
    with main_server().client() as client:
        response = client.post(f"/v2/models/{MODEL}/infer", content=body, headers=headers)
        assert_error(response, 422, "id", "unicode")
        unicode_id = "名前\u202e<x>"  # any other text is echoed as it came
        assert client.post(f"/v2/models/{MODEL}/infer", json=infer_body(id=unicode_id)).json()["id"] == unicode_id


@pytest.mark.parametrize("content_type", ["application/json", None])
def test_infer_data_nested_too_deeply_is_a_400_not_a_500(content_type):
    """The check for binary data after the JSON re-parsed the body and its RecursionError escaped as a 500."""
    deep = json.dumps(infer_body()).replace('"data": [[', '"data": ' + "[" * 100_000 + "]" * 100_000 + ", [[", 1)
    headers = {"content-type": content_type} if content_type else {}
    with main_server().client() as client:
        response = client.post(f"/v2/models/{MODEL}/infer", content=deep, headers=headers)
    assert_error(response, 400, "nested too deeply")


# -- hardening headers -------------------------------------------------------------------------------
def csp(response) -> dict[str, str]:
    """The Content-Security-Policy as ``{directive: sources}``."""
    directives = (part.strip().split(" ", 1) for part in response.headers["content-security-policy"].split(";"))
    return {d[0]: d[1] if len(d) > 1 else "" for d in directives if d[0]}


def test_every_response_is_nosniff_and_unframeable_and_pages_keep_their_policies():
    with main_server().client() as client:
        responses = {
            "page": client.get("/"),
            "swagger": client.get("/docs"),
            "redoc": client.get("/redoc"),
            "oauth2 redirect": client.get("/docs/oauth2-redirect"),
            "script": client.get("/page/page.js"),
            "models": client.get("/v1/models"),
            "openapi": client.get("/openapi.json"),
            "metrics": client.get("/metrics"),
            "404 echoing the path": client.get("/<script>alert(1)</script>"),
            "422": client.post("/v1/register", json={}),
            "405": client.options("/v1/register"),
            "head": client.head("/v2/health/ready"),
        }
    for name, response in responses.items():
        assert response.status_code < 500, name
        assert response.headers["x-content-type-options"] == "nosniff", name
        assert response.headers["x-frame-options"] == "DENY", name
        assert response.headers["referrer-policy"] == "no-referrer", name
        assert csp(response)["frame-ancestors"] == "'none'", name
    assert csp(responses["page"])["default-src"] == "'self'"  # the page's own policy, framing added
    assert "'unsafe-inline'" in csp(responses["swagger"])["script-src"]  # the API pages' bootstrap scripts run
    assert "'unsafe-inline'" in csp(responses["oauth2 redirect"])["script-src"]
    for name in ("models", "404 echoing the path", "422", "script"):  # not pages: the browser may load nothing
        assert csp(responses[name])["default-src"] == "'none'", name


def test_the_request_contexts_own_413_carries_the_headers_too():
    """The Content-Length check answers before any route runs, from the outermost layer but one."""
    url = urlsplit(main_server().url)
    with socket.create_connection((url.hostname, url.port), timeout=10) as sock:
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     b"Content-Length: 1000000000000\r\n\r\n")
        head = read_response(sock).split(b"\r\n\r\n", 1)[0].lower()
    assert head.startswith(b"http/1.1 413") and b"x-content-type-options: nosniff" in head, head


CHROMIUM = os.environ.get("MFGNET_CHROMIUM") or shutil.which("chromium") or shutil.which("google-chrome")
CHROMEDRIVER = os.environ.get("MFGNET_CHROMEDRIVER") or shutil.which("chromedriver")


@pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None, reason="Chromium or chromedriver not installed "
                    "(apt-get install chromium chromium-driver; `make test` does it)")
def test_chromium_refuses_to_show_the_page_in_another_sites_frame(tmp_path):
    """A page of another origin (another port) frames the page and Swagger UI: Chromium refuses both (clickjacking).
    That the page itself works under its policy is ``test_page_browser.py``'s, which fails on any console error."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    url = main_server().url
    (tmp_path / "frames.html").write_text(f"<!doctype html><iframe src='{url}/'></iframe><iframe src='{url}/docs'>")
    other = ThreadingHTTPServer(("127.0.0.1", 0), partial(QuietFiles, directory=str(tmp_path)))
    threading.Thread(target=other.serve_forever, daemon=True).start()
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
                "--disable-background-networking"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=options, service=Service(executable_path=CHROMEDRIVER))
    try:
        driver.set_page_load_timeout(20)
        driver.get(f"http://127.0.0.1:{other.server_address[1]}/frames.html")
        shown = []
        for frame in driver.find_elements(By.TAG_NAME, "iframe"):
            driver.switch_to.frame(frame)
            shown.append(driver.execute_script("return location.href"))
            driver.switch_to.default_content()
        refused = [e["message"] for e in driver.get_log("browser") if "frame-ancestors" in e["message"]]
    finally:
        driver.quit()
        other.shutdown()
    assert len(shown) == 2 and all(href.startswith("chrome-error:") for href in shown), shown
    assert len(refused) == 2, refused


class QuietFiles(SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


# -- slow or silent connections (slowloris) ----------------------------------------------------------
@pytest.fixture(scope="module")
def slow_headers_server():
    server = start_subprocess_server("slow-headers", MFGNET_HEADER_TIMEOUT_S=str(HEADER_TIMEOUT_S),
                                     MFGNET_KEEP_ALIVE_S=str(KEEP_ALIVE_S))
    yield server
    server.stop()


def connect(server) -> socket.socket:
    url = urlsplit(server.url)
    return socket.create_connection((url.hostname, url.port), timeout=KEEP_ALIVE_S + 5)


def read_response(sock: socket.socket) -> bytes:
    """Everything the server sends until it closes the connection or answers once (by its Content-Length)."""
    data = b""
    while True:
        chunk = sock.recv(65536)
        if not chunk:
            return data
        data += chunk
        head, sep, body = data.partition(b"\r\n\r\n")
        length = [line.split(b":", 1)[1] for line in head.lower().split(b"\r\n") if line.startswith(b"content-length:")]
        if sep and length and len(body) >= int(length[0]):
            return data


def test_headers_sent_a_line_at_a_time_get_a_408_and_the_connection_is_closed(slow_headers_server):
    """uvicorn alone kept such a connection for as long as its lines kept coming."""
    with connect(slow_headers_server) as sock:
        started = time.monotonic()
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n")
        try:
            for i in range(40):  # 10 s of header lines, one every 0.25 s
                time.sleep(0.25)
                sock.sendall(b"X-Slow-%d: y\r\n" % i)
        except OSError:  # closed by the server while we were still sending
            pass
        answer = read_response(sock)
        assert sock.recv(1) == b""  # then closed
    elapsed = time.monotonic() - started
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408"), answer[:200]
    assert "MFGNET_HEADER_TIMEOUT_S" in json.loads(body)["error"]
    assert HEADER_TIMEOUT_S <= elapsed < HEADER_TIMEOUT_S + 3, elapsed
    # Written below the ASGI layer, past the security headers' middleware: the 408 carries them itself.
    headers = dict(line.decode().lower().split(": ", 1) for line in head.split(b"\r\n")[1:])
    assert headers["x-content-type-options"] == "nosniff", headers
    assert headers["x-frame-options"] == "deny", headers
    assert headers["referrer-policy"] == "no-referrer", headers
    assert headers["content-security-policy"] == "default-src 'none'; frame-ancestors 'none'", headers


def test_a_connection_that_sends_nothing_is_closed_after_the_keep_alive_timeout(slow_headers_server):
    with connect(slow_headers_server) as sock:
        started = time.monotonic()
        assert sock.recv(1) == b""  # closed, with no answer
    assert KEEP_ALIVE_S - 0.5 <= time.monotonic() - started < KEEP_ALIVE_S + 3


def test_kept_alive_connections_and_headers_within_the_deadline_still_work(slow_headers_server):
    request = b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n\r\n"
    with connect(slow_headers_server) as sock:
        sock.sendall(request[:20])
        time.sleep(HEADER_TIMEOUT_S / 2)  # slow, but within the deadline
        sock.sendall(request[20:])
        assert read_response(sock).startswith(b"HTTP/1.1 200")
        time.sleep(HEADER_TIMEOUT_S * 1.5)  # idle between requests: the keep-alive timeout's, not the header one's
        sock.sendall(request)
        assert read_response(sock).startswith(b"HTTP/1.1 200")


def header_timeouts(server) -> float:
    """``mfgnet_http_header_timeouts_total`` on the server's ``/metrics``."""
    with server.client() as client:
        match = re.search(r"^mfgnet_http_header_timeouts_total (\S+)$", client.get("/metrics").text, re.MULTILINE)
    assert match, "mfgnet_http_header_timeouts_total is not exported"
    return float(match.group(1))


def stall_headers(server) -> bytes:
    """A request line and one header, then nothing: the server's answer once it closes the connection."""
    with connect(server) as sock:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n")
        answer = read_response(sock)
        assert sock.recv(1) == b""
    return answer


def test_each_header_timeout_is_counted_once_and_written_as_an_access_line(slow_headers_server):
    """They were a warning line only: neither /metrics nor the access log showed them."""
    before = header_timeouts(slow_headers_server)
    answers: list[bytes] = []
    stalled = [threading.Thread(target=lambda: answers.append(stall_headers(slow_headers_server))) for _ in range(2)]
    for thread in stalled:
        thread.start()
    with slow_headers_server.client() as client:  # normal requests meanwhile, a kept-alive connection's among them
        for _ in range(3):
            assert client.get("/v2/health/live").status_code == 200
    for thread in stalled:
        thread.join(KEEP_ALIVE_S + 10)
    assert [answer[:12] for answer in answers] == [b"HTTP/1.1 408"] * 2
    assert header_timeouts(slow_headers_server) == before + 2
    assert header_timeouts(slow_headers_server) == before + 2  # the scrapes themselves add nothing

    ids = {re.search(rb"x-request-id: (\w+)", answer).group(1).decode() for answer in answers}
    lines = {line.get("request_id"): line for line in slow_headers_server.log_lines()
             if line.get("logger") == "mfgnet.access" and line.get("status") == 408}
    assert ids <= set(lines), (ids, lines)
    for request_id in ids:
        line = lines[request_id]
        assert line["msg"] == "request" and line["client"] == "127.0.0.1" and "MFGNET_HEADER_TIMEOUT_S" in line["error"]
        assert HEADER_TIMEOUT_S * 1000 <= line["ms"] < (HEADER_TIMEOUT_S + 3) * 1000, line
