"""Default requests among abandoned ones: a real server, with checkouts side by side, under a mix of clients.

Each of ``--requests`` clients (``--clients`` at a time) sends, by a seeded draw, a default 768-point dense request
(half of them), a search at the options' limits whose client gives up after 0.05-0.6 s, or one that waits past the
server's deadline (a quarter each). Reported per server: the statuses by kind, whether every default request answered
200 got the server's own pose for it, the slots still taken 2 s after the last answer, and the status of one more
default request then. A server that leaves abandoned work running refuses or times out the default requests behind
it (``docs/decisions/0043-cancel-registrations-nobody-waits-for.md``)::

    python -m bench.abandoned_requests --compare-root /tmp/before
"""

from __future__ import annotations

import argparse
import random
import re
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

from bench.default_request import dense_bodies
from bench.http_latency import Server
from bench.report_io import (
    checked,
    emit_report,
    json_destination,
    machine_info,
    non_negative_int,
    positive_int,
    require_checkouts,
)
from model.cli_inputs import require_shapes

HEADERS = {"content-type": "application/json"}
DEADLINE_S = 3.0
KINDS = ("default", "default", "impatient", "heavy")  # drawn per request


def heavy_body(points: int = 8_000, seed: int = 0) -> dict:
    """A search at the options' limits on random clouds: tens of seconds of work."""
    rng = np.random.default_rng(seed)
    return {"source": rng.normal(size=(points, 3)).tolist(), "target": rng.normal(size=(points, 3)).tolist(),
            "iterations": 8, "keypoints": 512, "refine": "none", "rotation_search": True}


def slots_taken(client: httpx.Client) -> float:
    match = re.search(r"^mfgnet_inference_slots_taken (\S+)$", client.get("/metrics").text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0


def run_mix(url: str, requests: int, clients: int, seed: int) -> dict:
    """The mix against the server at ``url``: statuses by kind, poses, slots afterwards."""
    default = dense_bodies(1)[0]
    heavy = heavy_body()
    with httpx.Client(base_url=url, timeout=120) as client:
        reference = client.post("/v1/register", content=default, headers=HEADERS).json()["transform"]

    def one(i: int) -> tuple[str, str, bool | None]:
        draw = random.Random(seed * 100_003 + i)
        kind = draw.choice(KINDS)
        timeout = draw.uniform(0.05, 0.6) if kind == "impatient" else 120
        try:
            with httpx.Client(base_url=url, timeout=timeout) as client:
                if kind == "default":
                    response = client.post("/v1/register", content=default, headers=HEADERS)
                else:
                    response = client.post("/v1/register", json=heavy)
        except httpx.TimeoutException:
            return kind, "client gave up", None
        same = response.json()["transform"] == reference if kind == "default" and response.is_success else None
        return kind, str(response.status_code), same

    started = time.perf_counter()
    with ThreadPoolExecutor(clients) as pool:
        answers = list(pool.map(one, range(requests)))
    seconds = time.perf_counter() - started
    time.sleep(2.0)
    with httpx.Client(base_url=url, timeout=120) as client:
        taken = slots_taken(client)
        after = client.post("/v1/register", content=default, headers=HEADERS).status_code
    counts = Counter(f"{kind} {status}" for kind, status, _ in answers)
    return {"statuses": dict(sorted(counts.items())), "seconds": round(seconds, 1),
            "default_answers_have_the_servers_pose": all(same for _, _, same in answers if same is not None),
            "slots_taken_2s_after": taken, "a_default_request_after": after}


def compare(roots: list[str | None], requests: int, clients: int, seed: int) -> dict:
    rows = []
    for root in roots:
        with Server(threads=1, max_concurrency=2, max_queue=8, cwd=root, models="general",
                    timeout_s=DEADLINE_S) as server:
            rows.append({"server_root": root or "(this checkout)", **run_mix(server.url, requests, clients, seed)})
    return {"benchmark": "abandoned_requests", "requests": requests, "clients": clients, "seed": seed,
            "deadline_s": DEADLINE_S, "servers": rows, "machine": machine_info(1)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare-root", action="append", default=[],
                        help="another checkout (repeatable)")
    parser.add_argument("--requests", type=positive_int, default=48)
    parser.add_argument("--clients", type=positive_int, default=8, help="clients at a time")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    checked(require_shapes, "test", "dense", None)  # the default requests' pairs
    json_destination(args.json)
    require_checkouts(parser, args.compare_root)
    report = compare([None, *args.compare_root], args.requests, args.clients, args.seed)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
