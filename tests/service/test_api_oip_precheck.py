"""An OIP ``infer`` body whose point count is too large where that is cheap to tell (the JSON header's declared shapes
with binary tensor data; the JSON values counted from the bytes otherwise) is refused with its 413 before the request
waits for a worker, as ``/v1/register``'s JSON bodies are (``test_api_json_precheck.py``): a busy server answers at
once, where it answered 504 once the deadline passed in the queue. The answer equals the one an idle server gives;
right-sized bodies, and JSON bodies whose count passes but whose cloud is over ``max_points`` (known only from the
parse), still wait for the worker.

A real server (uvicorn in a thread of this process, the bundled model, real HTTP) with one worker and a short deadline;
a route added to the app holds that worker.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from api_server import Server, assert_error, held_worker_server, wait_for

LIMIT = 1_000  # the server's max_points
DEADLINE_S = 2.0  # the server's queue deadline: a refused body answers long before it, even on a loaded host
INFER = "/v2/models/clean/infer"
HEADER = "Inference-Header-Content-Length"
FAST = {"iterations": 1, "keypoints": 16, "refine": "none"}
RNG = np.random.default_rng(0)
SMALL = RNG.normal(size=(300, 3)).astype(np.float32)
HUGE = RNG.normal(size=(5 * LIMIT, 3)).astype(np.float32)  # 15,000 values: above 4 x 2 x 1,000 + 4,096
JUST_OVER = RNG.normal(size=(LIMIT + 1, 3)).astype(np.float32)  # within the count; over max_points


def binary(source: np.ndarray, target: np.ndarray, shape: list[int] | None = None) -> tuple[bytes, dict]:
    """A binary tensor data body (``shape``: SOURCE's declared shape, its own by default) and its headers."""
    inputs, data = [], b""
    for name, cloud, declared in (("SOURCE", source, shape), ("TARGET", target, None)):
        raw = cloud.astype("<f4").tobytes()
        inputs.append({"name": name, "shape": declared or list(cloud.shape), "datatype": "FP32",
                       "parameters": {"binary_data_size": len(raw)}})
        data += raw
    head = json.dumps({"inputs": inputs, "parameters": FAST}).encode()
    return head + data, {HEADER: str(len(head)), "content-type": "application/octet-stream"}


def as_json(source: np.ndarray, target: np.ndarray) -> tuple[bytes, dict]:
    inputs = [{"name": name, "shape": list(cloud.shape), "datatype": "FP32", "data": cloud.round(4).tolist()}
              for name, cloud in (("SOURCE", source), ("TARGET", target))]
    return json.dumps({"inputs": inputs, "parameters": FAST}).encode(), {"content-type": "application/json"}


EARLY = [  # (what, (body, headers), words of the 413)
    ("binary SOURCE over max_points", binary(HUGE, SMALL), ("SOURCE has 5000 points", "MFGNET_MAX_POINTS")),
    ("binary TARGET over max_points", binary(SMALL, HUGE), ("TARGET has 5000 points", "MFGNET_MAX_POINTS")),
    ("a declared shape beyond its bytes", binary(SMALL, SMALL, [10**9, 3]), ("SOURCE has 1000000000 points",)),
    ("JSON data of too many values", as_json(HUGE, SMALL), ("values", "two clouds of at most 1000 points")),
]
WAITING = [  # right-sized, or over max_points by a count the JSON's parse tells
    ("binary, right-sized", binary(SMALL, SMALL)),
    ("JSON, right-sized", as_json(SMALL, SMALL)),
    ("JSON, just over max_points", as_json(JUST_OVER, SMALL)),
]


@pytest.fixture(scope="module")
def held() -> Iterator[tuple[Server, object, threading.Event]]:
    server, limiter, release = held_worker_server(timeout_s=DEADLINE_S, max_points=LIMIT)
    yield server, limiter, release
    release.set()
    server.stop()


def post(server: Server, path: str, body: bytes, headers: dict) -> tuple[object, float]:
    with server.client() as client:
        started = time.perf_counter()
        response = client.post(path, content=body, headers=headers)
        return response, time.perf_counter() - started


def test_an_infer_body_over_max_points_is_413_at_once_on_a_busy_server(held):
    server, limiter, release = held
    with ThreadPoolExecutor(1) as pool:
        try:  # the worker released whatever happens: the pool waits for the holder on the way out
            holder = pool.submit(post, server, "/test/hold", b"{}", {"content-type": "application/json"})
            wait_for(lambda: limiter.running == 1, what="the worker held")
            busy = []
            for what, (body, headers), words in EARLY:
                response, took = post(server, INFER, body, headers)
                busy.append(assert_error(response, 413, *words))
                assert took < DEADLINE_S, (what, took)  # the old tree: 504 after the deadline
                assert limiter.taken == 1, what  # the holder's slot only: the refused request's is freed
            for what, (body, headers) in WAITING:
                response, _ = post(server, INFER, body, headers)
                assert response.status_code == 504, (what, response.text[:200])  # waited for the worker, as before
        finally:
            release.set()
        assert holder.result()[0].status_code == 200
    wait_for(lambda: limiter.taken == 0, what="the slots freed")
    for (what, (body, headers), _), early in zip(EARLY, busy, strict=True):  # an idle server: the same answer
        response, _ = post(server, INFER, body, headers)
        assert response.status_code == 413 and response.json() == early, what
    response, _ = post(server, INFER, *as_json(JUST_OVER, SMALL))
    assert_error(response, 413, "SOURCE has 1001 points", "MFGNET_MAX_POINTS")  # the decoder's parse
    for what, (body, headers) in WAITING[:2]:
        response, _ = post(server, INFER, body, headers)
        assert response.status_code == 200, (what, response.text[:300])
