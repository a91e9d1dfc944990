"""``/v1/register/aligned`` holds its slot until the moved file has been sent: a client that does not read its answer
keeps one place in MFGNET_MAX_CONCURRENCY + MFGNET_MAX_QUEUE (not an unbounded count of moved files in /tmp), and is
dropped after MFGNET_BODY_TIMEOUT_S without reading."""

from __future__ import annotations

import io
import socket
import time

import httpx
import numpy as np
import pytest
from api_server import start_subprocess_server, synthetic_pair
from prometheus_client.parser import text_string_to_metric_families

STALL_S = 2.0
BOUNDARY = b"b0undary"


def one_worker(name: str, queue: int):
    """A server of one worker and ``queue`` queue places whose stalled bodies and answers wait ``STALL_S``."""
    server = start_subprocess_server(name, MFGNET_MAX_CONCURRENCY="1", MFGNET_MAX_QUEUE=str(queue),
                                     MFGNET_BODY_TIMEOUT_S=str(STALL_S))
    yield server
    server.stop()


@pytest.fixture(scope="module")
def one_slot_server():
    yield from one_worker("aligned_slot", 0)


def aligned_request(points: np.ndarray) -> bytes:
    """A raw ``POST /v1/register/aligned`` of ``points [N, 3]`` as ``.npy``, moved by a shift."""
    buffer = io.BytesIO()
    np.save(buffer, points)
    body = (b"--" + BOUNDARY + b'\r\nContent-Disposition: form-data; name="transform"\r\n\r\n'
            b"[[1,0,0,0.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\r\n--" + BOUNDARY
            + b'\r\nContent-Disposition: form-data; name="source"; filename="scan.npy"\r\n'
              b"Content-Type: application/octet-stream\r\n\r\n" + buffer.getvalue() + b"\r\n--" + BOUNDARY + b"--\r\n")
    return (b"POST /v1/register/aligned HTTP/1.1\r\nHost: test\r\nContent-Type: multipart/form-data; boundary="
            + BOUNDARY + b"\r\nContent-Length: " + str(len(body)).encode() + b"\r\n\r\n" + body)


def test_an_unread_aligned_answer_keeps_its_slot_until_the_stall_limit(one_slot_server):
    pair = synthetic_pair(0)
    small = {"source": pair.source.tolist(), "target": pair.target.tolist(), "refine": "none"}
    points = np.random.default_rng(0).uniform(-1, 1, size=(2_000_000, 3)).astype(np.float32)  # a 24 MB answer
    url = httpx.URL(one_slot_server.url)
    with socket.create_connection((url.host, url.port), timeout=30) as reader:
        reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        reader.sendall(aligned_request(points))
        head = reader.recv(4096)  # the status line and headers; the rest is left unread
        assert head.startswith(b"HTTP/1.1 200"), head[:200]
        with one_slot_server.client() as client:
            busy = client.post("/v1/register", json=small)
            assert busy.status_code == 503, busy.text  # the unread answer holds the one slot (before: 200)
            deadline = time.monotonic() + STALL_S + 10
            while (answer := client.post("/v1/register", json=small)).status_code == 503:
                assert time.monotonic() < deadline, "the stalled answer kept its slot"
                time.sleep(0.5)
            assert answer.status_code == 200, answer.text
        # the dropped answer's connection is closed by the server, not left open until its buffers drain, and logged
        # as a 499 (it was a 200 that never completed, with uvicorn's "without completing response" error)
        lines = [line for line in one_slot_server.log_lines() if line.get("route") == "/v1/register/aligned"]
        assert [line["status"] for line in lines] == [499], lines
        assert not [line for line in one_slot_server.log_lines() if "without completing response" in str(line)]


@pytest.fixture(scope="module")
def one_worker_server():
    yield from one_worker("aligned_answers", 2)


def test_aligned_answers_at_once_are_as_many_as_the_workers(one_worker_server):
    """With one worker and free queue places, a second aligned request while the first answer is unread is a 503
    naming the aligned files (the moved files on disk stay as many as MFGNET_MAX_CONCURRENCY); a registration is
    not held up."""
    pair = synthetic_pair(0)
    small = {"source": pair.source.tolist(), "target": pair.target.tolist(), "refine": "none"}
    points = np.random.default_rng(1).uniform(-1, 1, size=(2_000_000, 3)).astype(np.float32)
    url = httpx.URL(one_worker_server.url)
    with socket.create_connection((url.host, url.port), timeout=30) as reader:
        reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        reader.sendall(aligned_request(points))
        assert reader.recv(4096).startswith(b"HTTP/1.1 200")
        with socket.create_connection((url.host, url.port), timeout=30) as second:
            second.sendall(aligned_request(points[:1000]))
            answer = b""
            while not answer.endswith(b"}") and (chunk := second.recv(65536)):  # headers, then the JSON error
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 503") and b"aligned file being written or sent" in answer, answer[:300]
        with one_worker_server.client() as client:
            assert client.post("/v1/register", json=small).status_code == 200  # the worker is free


def downloads_counted(server, status: str) -> float:
    """``mfgnet_http_requests_total`` of the aligned route at ``status``, from the server's ``/metrics``."""
    with server.client() as client:
        families = text_string_to_metric_families(client.get("/metrics").text)
    return sum(sample.value for family in families for sample in family.samples
               if sample.name == "mfgnet_http_requests_total" and sample.labels.get("status") == status
               and sample.labels.get("route") == "/v1/register/aligned")


def aligned_downloads(server) -> list[dict]:
    """The access lines of the server's aligned downloads (not its busy refusals)."""
    return [line for line in server.log_lines()
            if line.get("route") == "/v1/register/aligned" and line["status"] != 503]


def test_an_aligned_answer_the_client_closes_part_way_is_a_499(one_worker_server):
    """A client that reads the start of its download and hangs up is counted and logged as 499, as a client that
    stops reading is (before: a 200, as if the whole file had been sent)."""
    points = np.random.default_rng(2).uniform(-1, 1, size=(2_000_000, 3)).astype(np.float32)  # a 24 MB answer
    url = httpx.URL(one_worker_server.url)
    before = len(aligned_downloads(one_worker_server))
    counted = downloads_counted(one_worker_server, "499")
    with socket.create_connection((url.host, url.port), timeout=30) as reader:
        reader.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        reader.sendall(aligned_request(points))
        received = b""
        while len(received) < 100_000:
            received += reader.recv(4096)
        assert received.startswith(b"HTTP/1.1 200")
    deadline = time.monotonic() + 10
    while len(lines := aligned_downloads(one_worker_server)) == before:
        assert time.monotonic() < deadline, "no access line for the download"
        time.sleep(0.2)
    assert [line["status"] for line in lines[before:]] == [499]
    assert downloads_counted(one_worker_server, "499") == counted + 1


def read_answer(sock: socket.socket) -> bytes:
    """One HTTP answer: its head and the ``Content-Length`` bytes of its body, and nothing more."""
    data = b""
    while b"\r\n\r\n" not in data:
        data += sock.recv(65536)
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n")
                  if line.lower().startswith(b"content-length"))
    while len(body) < length:
        body += sock.recv(65536)
    return head + b"\r\n\r\n" + body


def test_an_aligned_answer_read_whole_is_a_200_when_the_client_closes_at_once(one_worker_server):
    """curl closes once it has read the Content-Length: the answer's end went out only after one more read of the
    file in a worker thread, so the server saw the client gone first and logged and counted a 499 (4-14 of 10-20
    downloads), though every byte had been received."""
    points = np.random.default_rng(3).uniform(-1, 1, size=(20_000, 3)).astype(np.float32)
    url = httpx.URL(one_worker_server.url)
    before, counted = len(aligned_downloads(one_worker_server)), downloads_counted(one_worker_server, "200")
    done = 0
    while done < 10:
        with socket.create_connection((url.host, url.port), timeout=30) as sock:
            sock.sendall(aligned_request(points))
            answer = read_answer(sock)
        if answer.startswith(b"HTTP/1.1 503"):  # the last download still holds the one slot: its end is being logged
            time.sleep(0.05)
            continue
        assert answer.startswith(b"HTTP/1.1 200"), answer[:200]
        done += 1
    deadline = time.monotonic() + 10
    while len(lines := aligned_downloads(one_worker_server)) < before + 10:
        assert time.monotonic() < deadline, "no access lines for the downloads"
        time.sleep(0.2)
    assert [line["status"] for line in lines[before:]] == [200] * 10
    assert downloads_counted(one_worker_server, "200") == counted + 10
