"""A JSON body of more values than ``max_points`` allow (``bodies.check_json_values``: bytes counted, no parse) is
refused with its 413 before the request waits for a worker, on ``/v1/register`` and ``/v1/register/batch``: a busy
server answers at once, where it answered 504 once the deadline passed in the queue. The answer equals the one an idle
server's decoder gives; right-sized bodies, and bodies whose count passes but whose cloud is over ``max_points`` (known
only from the parse), still wait for the worker.

A real server (uvicorn in a thread of this process, the bundled model, real HTTP) with one worker and a short deadline;
a route added to the app holds that worker, as in ``test_api_upload_precheck.py``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from api_server import Server, assert_error, held_worker_server, wait_for

LIMIT = 1_000  # the server's max_points
DEADLINE_S = 0.5
FAST = {"iterations": 1, "keypoints": 16}
RNG = np.random.default_rng(0)
SMALL = RNG.normal(size=(300, 3)).round(4).tolist()
HUGE = RNG.normal(size=(5 * LIMIT, 3)).round(4).tolist()  # 20,000 values: above 4 x 2 x 1,000 + 4,096
JUST_OVER = RNG.normal(size=(LIMIT + 1, 3)).round(4).tolist()  # within the count; over max_points


@pytest.fixture(scope="module")
def held() -> Iterator[tuple[Server, object, threading.Event]]:
    server, limiter, release = held_worker_server(timeout_s=DEADLINE_S, max_points=LIMIT)
    yield server, limiter, release
    release.set()
    server.stop()


def post(server: Server, path: str, body: dict) -> tuple[object, float]:
    with server.client() as client:
        started = time.perf_counter()
        response = client.post(path, json=body)
        return response, time.perf_counter() - started


CASES = [
    ("/v1/register", {"source": HUGE, "target": SMALL, **FAST}, "two clouds of at most 1000 points"),
    ("/v1/register/batch", {"pairs": [{"source": SMALL, "target": HUGE}]}, "a batch's clouds"),
]


def test_a_json_body_of_too_many_values_is_413_at_once_on_a_busy_server(held):
    server, limiter, release = held
    with ThreadPoolExecutor(1) as pool:
        try:  # the worker released whatever happens: the pool waits for the holder on the way out
            holder = pool.submit(post, server, "/test/hold", {})
            wait_for(lambda: limiter.running == 1, what="the worker held")
            busy = []
            for path, body, named in CASES:
                response, took = post(server, path, body)
                busy.append(assert_error(response, 413, "values", named))
                assert took < DEADLINE_S, (path, took)  # the old tree: 504 after the deadline
                assert limiter.taken == 1  # the holder's slot only: the refused request's is freed
            for path, body in (("/v1/register", {"source": SMALL, "target": SMALL, **FAST}),
                               ("/v1/register", {"source": JUST_OVER, "target": SMALL, **FAST})):
                response, took = post(server, path, body)
                assert_error(response, 504, "MFGNET_TIMEOUT_S")  # waited for the worker, as before
        finally:
            release.set()
        assert holder.result()[0].status_code == 200
    wait_for(lambda: limiter.taken == 0, what="the slots freed")
    for (path, body, _), early in zip(CASES, busy, strict=True):  # an idle server: the same answer
        response, _ = post(server, path, body)
        assert response.status_code == 413 and response.json() == early
    response, _ = post(server, "/v1/register", {"source": JUST_OVER, "target": SMALL, **FAST})
    assert_error(response, 413, "source has 1001 points", "MFGNET_MAX_POINTS")  # the decoder's parse
    response, _ = post(server, "/v1/register", {"source": SMALL, "target": SMALL, **FAST})
    assert response.status_code == 200, response.text
