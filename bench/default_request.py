"""Latency of a request with no options: 768-point dense ModelNet40 pairs over HTTP, checkouts side by side.

Each server (this checkout, and every ``--compare-root`` checkout) serves the same copy of this checkout's
bundled ``general`` model with its own code and defaults; every round sends the same JSON body (the two
clouds, nothing else) to each server in turn, so load on the machine slows them alike::

    python -m bench.default_request --compare-root /tmp/before --requests 40
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx
import numpy as np

from bench.http_latency import Server
from bench.report_io import (
    checked,
    emit_report,
    json_destination,
    machine_info,
    positive_int,
    provenance,
    require_checkouts,
)
from model.cli_inputs import require_shapes


def dense_bodies(count: int, seed: int = 0) -> list[bytes]:
    """JSON bodies of ``count`` seeded dense test pairs (independent 768-point samples), no option."""
    from model.data import make_test_pairs

    pairs = make_test_pairs("dense", "test", count=count, seed=seed)
    return [json.dumps({"source": s.tolist(), "target": t.tolist()}).encode()
            for s, t in zip(pairs["source"], pairs["target"], strict=True)]


def compare(roots: list[str | None], requests: int, pairs: int = 16, threads: int = 2) -> dict:
    """p50 / p95 client ms of default requests per server (``None``: this checkout), rounds taking turns."""
    from service.manifest import bundled_models_dir

    made_by = provenance([bundled_models_dir() / "general"])  # this checkout's; --compare-root ones: their roots
    models = Path(tempfile.mkdtemp(prefix="mfgnet-default-request-"))
    shutil.copytree(bundled_models_dir() / "general", models / "general")
    bodies = dense_bodies(pairs)
    headers = {"content-type": "application/json"}
    try:
        with ExitStack() as stack:
            servers = [stack.enter_context(Server(threads=threads, cwd=root, model_dirs=str(models)))
                       for root in roots]
            clients = [stack.enter_context(httpx.Client(base_url=s.url, timeout=120)) for s in servers]
            times: list[list[float]] = [[] for _ in servers]
            searched = [0 for _ in servers]
            for i in range(-1, requests):  # one untimed warm-up round
                order = range(len(clients)) if i % 2 == 0 else reversed(range(len(clients)))
                for k in order:
                    tic = time.perf_counter()
                    response = clients[k].post("/v1/register", content=bodies[i % len(bodies)], headers=headers)
                    elapsed = 1000 * (time.perf_counter() - tic)
                    response.raise_for_status()
                    if i >= 0:
                        times[k].append(elapsed)
                        searched[k] += "search" in response.json()["timing_ms"]
    finally:
        shutil.rmtree(models, ignore_errors=True)
    rows = [{"server_root": root or "(this checkout)", "p50_ms": round(float(np.percentile(t, 50)), 2),
             "p95_ms": round(float(np.percentile(t, 95)), 2), "searched": searched[k]}
            for k, (root, t) in enumerate(zip(roots, times, strict=True))]
    report = {"benchmark": "default_request", "requests": requests, "pairs": pairs, "servers": rows,
              "machine": machine_info(threads), "provenance": made_by}
    if len(rows) > 1:
        report["p50_ratio_to_first_compared"] = round(rows[0]["p50_ms"] / rows[1]["p50_ms"], 3)
    return report


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--compare-root", action="append", default=[],
                        help="another checkout (repeatable)")
    parser.add_argument("--requests", type=positive_int, default=40, help="timed rounds")
    parser.add_argument("--pairs", type=positive_int, default=16, help="distinct seeded dense pairs, cycled")
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    checked(require_shapes, "test", "dense", None)  # the requests' pairs
    json_destination(args.json)
    require_checkouts(parser, args.compare_root)
    report = compare([None, *args.compare_root], args.requests, args.pairs)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
