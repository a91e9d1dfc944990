"""The cap on open connections (``MFGNET_MAX_CONNECTIONS``, ``service/api/http_protocol.py``) against a real server
process: idle connections make room for new ones (probes get in), and when every connection is busy with a request a
new one is answered 503 with Retry-After at once; the open-file limit is raised and the cap fitted under it."""

from __future__ import annotations

import contextlib
import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from api_server import REPO, start_subprocess_server
from prometheus_client.parser import text_string_to_metric_families

CAP = 8


@pytest.fixture(scope="module")
def capped_server():
    server = start_subprocess_server("capped", MFGNET_MAX_CONNECTIONS=str(CAP))
    yield server
    server.stop()


def connect(server) -> socket.socket:
    url = urlsplit(server.url)
    return socket.create_connection((url.hostname, url.port), timeout=10)


def closed_by_server(sock: socket.socket, within_s: float) -> bool:
    """Whether the server closed ``sock`` (EOF, or a reset) within ``within_s`` seconds."""
    sock.settimeout(within_s)
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def answer(sock: socket.socket, timeout_s: float = 10) -> bytes:
    """Everything the server sends until it closes the connection."""
    sock.settimeout(timeout_s)
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    return data


def get(sock: socket.socket, path: str, timeout_s: float = 10) -> bytes:
    sock.sendall(b"GET %s HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n" % path.encode())
    return answer(sock, timeout_s)


def test_idle_connections_beyond_the_cap_make_room_and_a_probe_gets_in(capped_server):
    """Without a cap all of them stayed open (for MFGNET_KEEP_ALIVE_S, 75 s): a few thousand held every file
    descriptor a soft nofile limit of 1024 gives, and the probes went unanswered."""
    idle = [connect(capped_server) for _ in range(3 * CAP)]
    try:
        time.sleep(0.3)  # every one accepted
        with connect(capped_server) as probe:
            started = time.monotonic()
            reply = get(probe, "/v2/health/live")
        assert reply.startswith(b"HTTP/1.1 200"), reply[:200]
        assert time.monotonic() - started < 2
        time.sleep(0.3)  # the closes sent
        closed = [closed_by_server(sock, 0.01) for sock in idle]
        # the longest idle were closed to make room; the newest stay open
        assert all(closed[: 2 * CAP]), closed
        assert not any(closed[-CAP + 1 :]), closed
    finally:
        for sock in idle:
            sock.close()


def test_connections_whose_headers_are_still_arriving_make_room_with_a_408(capped_server):
    """Slowloris connections (a request line, then nothing: kept until MFGNET_HEADER_TIMEOUT_S, 15 s) cannot fill
    the cap: the one whose headers began first is answered 408 and closed."""
    slow = [connect(capped_server) for _ in range(CAP)]
    try:
        for sock in slow:
            sock.sendall(b"GET /v2/health/live HTTP/1.1\r\n")
            time.sleep(0.01)  # in this order
        time.sleep(0.3)
        with connect(capped_server) as probe:
            reply = get(probe, "/v2/health/live")
        assert reply.startswith(b"HTTP/1.1 200"), reply[:200]
        first = answer(slow[0], timeout_s=2)
        assert first.startswith(b"HTTP/1.1 408") and b"MFGNET_MAX_CONNECTIONS" in first, first[:300]
        time.sleep(0.3)
        assert not any(closed_by_server(sock, 0.01) for sock in slow[1:])
    finally:
        for sock in slow:
            sock.close()


TOO_LARGE = (b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
             b"Content-Length: 104857600\r\n\r\n{")  # over max_body_bytes (64 MiB): a 413 before the body is read


def answered_early(server) -> socket.socket:
    """A connection whose request was answered 413 from its Content-Length, its body still to come."""
    sock = connect(server)
    sock.sendall(TOO_LARGE)
    sock.settimeout(5)
    reply = b""
    while b"\r\n\r\n" not in reply or not reply.endswith(b"}"):  # the whole answer: its JSON body ends it
        reply += sock.recv(65536)
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]
    return sock


def test_connections_answered_before_their_body_make_room(capped_server):
    """uvicorn read the rest of such a body for as long as it kept coming, with no timer: connections answered early
    and then fed a byte now and then held places of the cap for good. Now they linger at most 30 s and go first."""
    early = [answered_early(capped_server) for _ in range(CAP)]
    try:
        for sock in early:
            sock.sendall(b" ")
        time.sleep(0.3)
        with connect(capped_server) as probe:
            reply = get(probe, "/v2/health/live")
        assert reply.startswith(b"HTTP/1.1 200"), reply[:200]
        assert closed_by_server(early[0], 2)  # the one answered first made room
    finally:
        for sock in early:
            sock.close()


@pytest.fixture(scope="module")
def plain_server():
    server = start_subprocess_server("early_refusals")
    yield server
    server.stop()


@pytest.mark.parametrize("connection", [b"", b"Connection: close\r\n"], ids=["keep-alive", "close"])
def test_a_refusal_before_the_body_reaches_a_client_still_sending_it(plain_server, connection):
    """A 415 answered before an 8 MB body is read: the client reads it whether or not it asked to close the connection
    (Python's urllib always does); before, a closing connection was shut with the body unread and the client got a
    reset instead of the answer."""
    body = b"x" * (8 << 20)
    with connect(plain_server) as sock:
        sock.settimeout(20)
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: text/plain\r\n"
                     b"Content-Length: %d\r\n%s\r\n" % (len(body), connection))
        sock.sendall(body)
        reply = sock.recv(65536)
    assert reply.startswith(b"HTTP/1.1 415"), reply[:200]


@pytest.mark.slow
def test_a_closing_client_that_sends_past_the_idle_linger_reads_its_refusal(plain_server):
    """Connection: close (Python's urllib) and a body that goes on arriving for 8 s after its 415: its rest is dropped
    as a kept-alive request's is (closed 5 s after the last piece, 30 s at most), so a client that reads only once its
    body is sent reads the 415; a fixed 5 s after the answer gave it a broken pipe instead."""
    with connect(plain_server) as sock:
        sock.settimeout(20)
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: text/plain\r\n"
                     b"Content-Length: %d\r\nConnection: close\r\n\r\n" % (80 << 16))
        for _ in range(80):
            sock.sendall(b"x" * (1 << 16))
            time.sleep(0.1)
        reply = sock.recv(65536)
    assert reply.startswith(b"HTTP/1.1 415"), reply[:200]


@pytest.mark.slow
def test_the_rest_of_an_answered_body_is_read_30_s_at_most(capped_server):
    with answered_early(capped_server) as sock:
        started = time.monotonic()
        closed = False
        while not closed and time.monotonic() - started < 40:
            try:
                sock.sendall(b" ")  # a byte every half second: never idle for LINGER_IDLE_S (5 s)
            except OSError:
                break
            closed = closed_by_server(sock, 0.5)
        elapsed = time.monotonic() - started
    assert 29 < elapsed < 32, elapsed


def refused(server) -> float:
    """``mfgnet_http_connections_refused_total`` on the server's ``/metrics``."""
    with connect(server) as sock:
        metrics = get(sock, "/metrics")
    assert metrics.startswith(b"HTTP/1.1 200"), metrics[:200]
    match = re.search(rb"^mfgnet_http_connections_refused_total (\S+)$", metrics, re.MULTILINE)
    assert match, metrics[-2000:]
    return float(match.group(1))


def test_when_every_connection_is_busy_a_new_one_is_refused_503_at_once(capped_server):
    before = refused(capped_server)
    busy = [connect(capped_server) for _ in range(CAP)]
    try:
        for sock in busy:  # a whole request but for its body: busy until MFGNET_BODY_TIMEOUT_S (15 s)
            sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Content-Length: 1000\r\n\r\n{")
        time.sleep(0.3)
        with connect(capped_server) as late:
            started = time.monotonic()
            reply = get(late, "/v2/health/live")
            elapsed = time.monotonic() - started
        head, _, body = reply.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503"), reply[:300]
        headers = dict(line.decode().lower().split(": ", 1) for line in head.split(b"\r\n")[1:])
        assert headers["retry-after"] == "1" and headers["content-type"] == "application/json", headers
        assert headers["x-content-type-options"] == "nosniff", headers
        assert "MFGNET_MAX_CONNECTIONS" in json.loads(body)["error"]
        assert elapsed < 2, elapsed
    finally:
        for sock in busy:
            sock.close()
    time.sleep(0.3)
    assert refused(capped_server) == before + 1  # the busy ones gone: served again, and the refusal counted


LIMITS = "from service.api.http_protocol import connection_limits as c; import resource; " \
         "print(c(1000), resource.getrlimit(resource.RLIMIT_NOFILE)[0])"


@pytest.mark.parametrize(("ulimit", "expected"), [
    ("-Sn 512", "(1000, 2048) 4096"),  # the soft limit raised to the hard one: room for the defaults
    ("-n 1024", "(462, 462) 1024"),  # a hard limit of 1024: the cap and backlog lowered to fit it
])
def test_the_open_file_limit_is_raised_and_the_cap_fitted_under_it(ulimit, expected):
    command = f"ulimit -Sn 512 && ulimit -Hn 4096 && ulimit {ulimit} && exec {sys.executable} -c '{LIMITS}'"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(["bash", "-c", command], capture_output=True, text=True, env=env, cwd=REPO, timeout=30)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == expected


IDLE = 2000
CONTAINER_SOFT_NOFILE = 1024  # a common container default (the hard limit is far higher)


def server_status(pid: int) -> tuple[int, float]:
    """The server's open file descriptors and resident memory (MiB)."""
    status = Path(f"/proc/{pid}/status").read_text().splitlines()
    rss = next(line for line in status if line.startswith("VmRSS")).split()[1]
    return len(os.listdir(f"/proc/{pid}/fd")), int(rss) / 1024


@pytest.mark.slow
def test_two_thousand_idle_connections_at_a_soft_nofile_of_1024_leave_the_probes_answered():
    """Before the cap, such a server's open files ran out (asyncio: "socket.accept() out of system resource", logged
    tens of thousands of times) and both probes timed out for as long as the connections stayed open (75 s)."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < IDLE + 200:
        pytest.skip(f"the hard nofile limit {hard} leaves no room for {IDLE} client sockets")
    resource.setrlimit(resource.RLIMIT_NOFILE, (CONTAINER_SOFT_NOFILE, hard))  # the server inherits it
    try:
        server = start_subprocess_server("idle-connections")
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, IDLE + 200), hard))  # this process's own sockets
    idle: list[socket.socket] = []
    try:
        pid = server.extra["proc"].pid
        fds_before, rss_before = server_status(pid)
        started = time.monotonic()
        idle = [connect(server) for _ in range(IDLE)]
        opened_s = time.monotonic() - started
        time.sleep(2)
        fds, rss = server_status(pid)
        answers = {}
        for path in ("/v2/health/live", "/v2/health/ready"):
            with connect(server) as probe:
                started = time.monotonic()
                try:
                    reply = get(probe, path, timeout_s=5)
                except TimeoutError:
                    reply = b"(no answer within 5 s)"
                answers[path] = (reply.split(b"\r\n", 1)[0].decode(), round(time.monotonic() - started, 3))
        accept_errors = server.log_path.read_text().count("out of system resource")
        print(f"\n{IDLE} idle connections opened in {opened_s:.1f} s; server file descriptors {fds_before} -> {fds}, "
              f"RSS {rss_before:.1f} -> {rss:.1f} MiB; probes {answers}; accept errors logged: {accept_errors}")
        assert all(status.startswith("HTTP/1.1 200") and seconds < 1 for status, seconds in answers.values()), answers
        assert accept_errors == 0
        assert fds < 1000 + 100, fds  # the default cap, and the server's own files
    finally:
        for sock in idle:
            sock.close()
        server.stop()


def registrations_counted(server) -> dict[str, float]:
    """``mfgnet_http_requests_total`` of POST ``/v1/register`` by status, from the server's ``/metrics``."""
    with server.client() as client:
        families = text_string_to_metric_families(client.get("/metrics").text)
    return {sample.labels["status"]: sample.value for family in families for sample in family.samples
            if sample.name == "mfgnet_http_requests_total" and sample.labels.get("route") == "/v1/register"
            and sample.labels.get("method") == "POST"}


def test_a_client_that_shuts_its_write_side_after_its_request_is_logged_499(plain_server):
    """A client that half-closes after its request (``shutdown(SHUT_WR)``, ``nc -N``) is taken as gone, as a full close
    cannot be told from it until an answer is written (uvicorn closes the connection on the EOF, as nginx and Go's
    server take it): the answer goes nowhere, and the access line and the metrics say 499. A registration that ended
    before its first look for a disconnect was logged and counted 200."""
    cloud = np.random.default_rng(0).normal(size=(256, 3)).round(4).tolist()
    body = json.dumps({"source": cloud, "target": cloud}).encode()
    before = registrations_counted(plain_server)
    request_id = f"half-closed-{time.monotonic_ns()}"
    with connect(plain_server) as sock:
        sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     b"Content-Length: %d\r\nX-Request-ID: %s\r\n\r\n%s" % (len(body), request_id.encode(), body))
        sock.shutdown(socket.SHUT_WR)
        assert answer(sock) == b""  # closed on the EOF, nothing answered
    deadline = time.monotonic() + 10
    while request_id not in plain_server.log_path.read_text() and time.monotonic() < deadline:
        time.sleep(0.05)
    line = next(json.loads(text) for text in plain_server.log_path.read_text().splitlines() if request_id in text)
    assert line["status"] == 499 and line["error"] == "the client closed the connection before the answer", line
    after = registrations_counted(plain_server)
    assert (after.get("499", 0) - before.get("499", 0), after.get("200", 0) - before.get("200", 0)) == (1, 0)



@pytest.mark.parametrize("connection", [b"", b"Connection: close\r\n"], ids=["keep-alive", "close"])
def test_an_answer_that_starts_a_linger_during_shutdown_does_not_hold_it_up(connection):
    """SIGTERM while a chunked upload is arriving; its 413 (over ``MFGNET_MAX_BODY_BYTES``) goes out during the grace,
    the client still sending: the rest of its body is dropped for ``REFUSED_LINGER_S``, not ``LINGER_IDLE_S``, so the
    server exits before its 5 s grace ends, with no error. The full linger held the server past its grace, which
    cancelled it and logged an error."""
    server = start_subprocess_server("linger_shutdown", MFGNET_MAX_BODY_BYTES=str(1 << 20))
    proc = server.extra["proc"]
    chunk = b"%x\r\n%s\r\n" % (1 << 16, b" " * (1 << 16))
    reply = b""
    try:
        with connect(server) as sock:
            sock.sendall(b"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                         b"Transfer-Encoding: chunked\r\n%s\r\n" % connection + chunk)
            time.sleep(0.5)  # the app is reading the body
            proc.terminate()
            stopped = time.monotonic()
            while proc.poll() is None and time.monotonic() - stopped < 15:
                with contextlib.suppress(OSError):
                    sock.sendall(chunk * 4)  # the body goes on arriving, over the limit after 16 chunks
                    if select.select([sock], [], [], 0)[0]:
                        reply += sock.recv(65536)
                time.sleep(0.1)
            elapsed = time.monotonic() - stopped
    finally:
        server.stop()
    errors = [line for line in server.log_path.read_text().splitlines() if '"level": "error"' in line]
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]
    assert elapsed < 4.5 and proc.returncode in (0, -signal.SIGTERM) and not errors, (elapsed, proc.returncode, errors)
