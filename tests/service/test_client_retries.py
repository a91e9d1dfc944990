"""Specification of ``MfgnetClient``'s ``busy_retries`` (and ``mfgnet register --busy-retries``) against a real server
made busy for real: one worker, no queue (``MFGNET_MAX_CONCURRENCY=1``, ``MFGNET_MAX_QUEUE=0``), and the only slot held
by a slow request, one whose JSON body arrives in two parts (the server admits a request before reading its body).
The holder sends the rest of its body once the client's first try has been refused (the server's metrics count the
503), and the client's retry, a ``Retry-After`` (1 s) later, finds the slot free. The same server serves a model that
failed to load (``tampered``), whose 503 has no ``Retry-After``.
"""

from __future__ import annotations

import json
import re
import socket
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from api_server import (
    Server,
    free_port,
    model_root,
    pair_json,
    start_subprocess_server,
    synthetic_pair,
    tampered_root,
    wait_for,
)
from typer.testing import CliRunner

from service.cli import app
from service.client import MfgnetClient, MfgnetError
from service.pointcloud_io import write_points

pytestmark = pytest.mark.serial  # waits of Retry-After (1 s) and "at once" bounds: run alone under `make test`

FAST = {"iterations": 1, "keypoints": 32}  # the smallest request the model takes
PAIR = synthetic_pair(0)
RETRY_AFTER_S = 1.0  # what the server asks for when busy (service.api.limiter.RETRY_AFTER_OVERLOADED_S)


@pytest.fixture(scope="module")
def busy() -> Iterator[Server]:
    """One worker and no queue (a second registration at once is a 503 with Retry-After), ``clean`` served and
    ``tampered`` failed (a 503 without Retry-After); ready, since one model is served."""
    server = start_subprocess_server("busy", MFGNET_MAX_CONCURRENCY="1", MFGNET_MAX_QUEUE="0",
                                     MFGNET_MODEL_DIRS=f"{model_root()},{tampered_root()}",
                                     MFGNET_STRICT_READINESS="false")
    yield server
    server.stop()


def metrics(server: Server) -> str:
    with server.client() as c:
        return c.get("/metrics").text


def answered(server: Server, status: int) -> float:
    """``POST /v1/register`` requests the server has answered with ``status``."""
    line = rf'^mfgnet_http_requests_total\{{(?=[^}}]*route="/v1/register")(?=[^}}]*status="{status}")[^}}]*\}} (\S+)$'
    return sum(float(value) for value in re.findall(line, metrics(server), re.MULTILINE))


class SlotHolder:
    """A cheap registration whose body stops after its first bytes: it holds the server's only slot until
    :meth:`finish` sends the rest (then it registers and frees the slot)."""

    def __init__(self, server: Server):
        body = json.dumps(pair_json(PAIR, **FAST)).encode()
        url = urlsplit(server.url)
        self.sock = socket.create_connection((url.hostname, url.port), timeout=30)
        self.sock.sendall(f"POST /v1/register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                          f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body[:20])
        self.rest = body[20:]

    def finish(self) -> bytes:
        """Sends the rest of the body; the server's whole answer."""
        self.sock.sendall(self.rest)
        data = b""
        while chunk := self.sock.recv(65536):
            data += chunk
        return data


@contextmanager
def holding_the_slot(server: Server) -> Iterator[SlotHolder]:
    holder = SlotHolder(server)
    try:
        wait_for(lambda: re.search(r"^mfgnet_inference_slots_taken 1\.0$", metrics(server), re.MULTILINE),
                 what="the slot taken")
        yield holder
    finally:
        holder.sock.close()


def clouds(upload: str, folder: Path) -> tuple[list, dict]:
    """``register``'s clouds and options for ``upload``: JSON lists, ``.npy`` uploads of arrays, or file paths."""
    if upload == "file paths":
        paths = [folder / "source.ply", folder / "target.pcd"]
        write_points(paths[0], PAIR.source)
        write_points(paths[1], PAIR.target)
        return [str(paths[0]), paths[1]], FAST
    return [PAIR.source, PAIR.target], {**FAST, "binary": upload == "npy"}


# -- a busy server: retried ----------------------------------------------------------------------------
@pytest.mark.parametrize("upload", ["json", "npy", "file paths"])
def test_a_busy_answer_is_sent_again_after_retry_after_and_succeeds_once_the_slot_is_free(busy, upload, tmp_path):
    """The retry sends the whole request again, files included: a cut or empty upload would be the server's 422."""
    args, options = clouds(upload, tmp_path)
    with MfgnetClient(busy.url, busy_retries=0) as client:
        reference = client.register(*args, **options)  # the server idle
    with holding_the_slot(busy) as holder, ThreadPoolExecutor(1) as pool, MfgnetClient(busy.url) as client:
        refused = answered(busy, 503)
        started = time.monotonic()
        call = pool.submit(client.register, *args, **options)
        wait_for(lambda: answered(busy, 503) > refused, what="the first try refused")
        assert holder.finish().startswith(b"HTTP/1.1 200")  # the slot is free again
        response = call.result(timeout=30)
        elapsed = time.monotonic() - started
    assert response["transform"] == reference["transform"]
    assert elapsed >= RETRY_AFTER_S  # it waited as long as Retry-After asked
    assert answered(busy, 503) - refused >= 1


def test_busy_retries_0_raises_the_503_at_once_naming_retry_after(busy):
    with holding_the_slot(busy) as holder, MfgnetClient(busy.url, busy_retries=0) as client:
        refused = answered(busy, 503)
        started = time.monotonic()
        with pytest.raises(MfgnetError) as info:
            client.register(PAIR.source, PAIR.target, **FAST)
        elapsed = time.monotonic() - started
        assert holder.finish().startswith(b"HTTP/1.1 200")
    assert info.value.status == 503 and info.value.retry_after == RETRY_AFTER_S
    assert "busy" in info.value.message and "Retry-After: 1; not retried: busy_retries=0" in str(info.value)
    assert elapsed < RETRY_AFTER_S and answered(busy, 503) - refused == 1


def test_a_server_that_stays_busy_is_retried_busy_retries_times_then_raised(busy):
    with holding_the_slot(busy) as holder, MfgnetClient(busy.url, busy_retries=1) as client:
        refused = answered(busy, 503)
        started = time.monotonic()
        with pytest.raises(MfgnetError) as info:
            client.register(PAIR.source, PAIR.target, **FAST)
        elapsed = time.monotonic() - started
        assert holder.finish().startswith(b"HTTP/1.1 200")
    assert info.value.status == 503 and info.value.retry_after == RETRY_AFTER_S
    assert "Retry-After: 1; given up after 1 retry: busy_retries=1" in str(info.value)
    assert elapsed >= RETRY_AFTER_S and answered(busy, 503) - refused == 2


def test_a_retry_whose_wait_would_outlast_the_timeout_is_not_made(busy):
    with holding_the_slot(busy) as holder, MfgnetClient(busy.url, timeout=1.0, busy_retries=2) as client:
        refused = answered(busy, 503)
        started = time.monotonic()
        with pytest.raises(MfgnetError) as info:
            client.register(PAIR.source, PAIR.target, **FAST)
        elapsed = time.monotonic() - started
        assert holder.finish().startswith(b"HTTP/1.1 200")
    assert info.value.status == 503 and "not retried" in str(info.value) and "past the 1 s timeout" in str(info.value)
    assert elapsed < RETRY_AFTER_S and answered(busy, 503) - refused == 1


# -- answers that are not retried -----------------------------------------------------------------------
def test_a_503_without_retry_after_and_a_4xx_are_not_retried(busy):
    """A model that failed to load stays failed: its 503 has no Retry-After and is raised at once, as a 422 is."""
    with MfgnetClient(busy.url, busy_retries=2) as client:
        failed, refused = answered(busy, 503), answered(busy, 422)
        started = time.monotonic()
        with pytest.raises(MfgnetError) as info:
            client.register(PAIR.source, PAIR.target, model="tampered", **FAST)
        elapsed = time.monotonic() - started
        with pytest.raises(MfgnetError) as bad:
            client.register(PAIR.source[:5], PAIR.target, **FAST)
    assert info.value.status == 503 and "tampered" in info.value.message and info.value.retry_after is None
    assert "Retry-After" not in str(info.value)
    assert elapsed < RETRY_AFTER_S and answered(busy, 503) - failed == 1
    assert bad.value.status == 422 and bad.value.retry_after is None and answered(busy, 422) - refused == 1


def test_a_server_that_cannot_be_reached_is_not_retried() -> None:
    with MfgnetClient(f"http://127.0.0.1:{free_port()}", timeout=1.0) as client, pytest.raises(MfgnetError) as info:
        client.models()
    assert info.value.status == 0 and info.value.retry_after is None and "on retry" not in info.value.message


@pytest.mark.parametrize("value", [-1, 1.5, "2"])
def test_busy_retries_must_be_a_whole_number_of_at_least_0(value) -> None:
    with pytest.raises(ValueError, match="busy_retries"):
        MfgnetClient(f"http://127.0.0.1:{free_port()}", busy_retries=value)


# -- the command line -----------------------------------------------------------------------------------
def test_register_server_retries_a_busy_server_and_busy_retries_0_fails_naming_retry_after(busy, tmp_path):
    src, tgt = tmp_path / "source.ply", tmp_path / "target.pcd"
    write_points(src, PAIR.source)
    write_points(tgt, PAIR.target)
    command = ["register", str(src), str(tgt), "--server", busy.url, "--iterations", "1", "--keypoints", "32", "--json"]
    runner = CliRunner()
    with holding_the_slot(busy) as holder:
        refused = runner.invoke(app, [*command, "--busy-retries", "0"])
        assert refused.exit_code == 1 and "503" in refused.stderr and "Retry-After" in refused.stderr, refused.output
        assert "not retried: --busy-retries 0" in refused.stderr, refused.stderr  # the flag, not the client's keyword
        failed = answered(busy, 503)
        with ThreadPoolExecutor(1) as pool:
            call = pool.submit(runner.invoke, app, command)  # the default: retried
            wait_for(lambda: answered(busy, 503) > failed, what="the first try refused")
            assert holder.finish().startswith(b"HTTP/1.1 200")
            result = call.result(timeout=30)
    assert result.exit_code == 0, result.output
    assert np.asarray(json.loads(result.stdout)["transform"]).shape == (4, 4)

