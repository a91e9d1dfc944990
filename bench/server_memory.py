"""A real server's memory through a short session of default requests (``docs/DEPLOYMENT.md``, "Current figures")::

    python -m bench.server_memory --models general
    python -m bench.server_memory                   # every bundled model

It starts ``mfgnet``'s HTTP app on 127.0.0.1 (``MFGNET_THREADS`` and ``MFGNET_MAX_CONCURRENCY`` 2, the server's
defaults), reads its resident memory (``VmRSS``) after start, after ``--small`` default registrations of seeded
1,024-point dense ModelNet40 test pairs, after one JSON registration of a ``--big-points`` pair (the same pair's
points and jittered copies of them), and its peak (``VmHWM``); ``searched`` counts the requests that ran the
rotation search. Every request is ``POST /v1/register`` with the two clouds as JSON and no option, so it runs what
a caller gets by default (``rotation_search: "auto"`` included).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import httpx
import numpy as np

from bench.http_latency import Server, rss_mb
from bench.latency import resize_cloud
from bench.report_io import checked, emit_report, json_destination, machine_info, non_negative_int, positive_int
from model.cli_inputs import require_shapes

SMALL_POINTS = 1024
THREADS = 2


def pairs(count: int, big_points: int, seed: int = 0) -> tuple[list[dict], dict]:
    """JSON bodies of ``count`` seeded 1,024-point dense test pairs, and one of ``big_points`` points per cloud."""
    from model.data import make_test_pairs

    test = make_test_pairs("dense", "test", count=count, seed=seed)
    rng = np.random.default_rng(seed)
    small = [{"source": resize_cloud(s, SMALL_POINTS, rng).tolist(),
              "target": resize_cloud(t, SMALL_POINTS, rng).tolist()}
             for s, t in zip(test["source"], test["target"], strict=True)]
    big = {"source": resize_cloud(test["source"][0], big_points, rng).tolist(),
           "target": resize_cloud(test["target"][0], big_points, rng).tolist()}
    return small, big


def measure(models: str | None, small_requests: int = 5, big_points: int = 100_000, seed: int = 0) -> dict:
    """Server RSS in MiB after start, after the small requests, after the big one, and its peak."""
    small, big = pairs(small_requests, big_points, seed)
    with Server(threads=THREADS, models=models) as server, httpx.Client(base_url=server.url, timeout=120) as client:

        def searched(body: dict) -> bool:
            """Register ``body``; whether the rotation search ran."""
            response = client.post("/v1/register", json=body)
            response.raise_for_status()
            return "search" in response.json()["timing_ms"]

        pid = server.proc.pid
        rss = {"after_start": rss_mb(pid)}
        searches = sum(searched(body) for body in small)
        rss["after_small"] = rss_mb(pid)
        searches += searched(big)
        rss["after_big"] = rss_mb(pid)
        rss["peak"] = rss_mb(pid, "VmHWM")
        served = [m["name"] for m in client.get("/v1/models").json()["models"]]
    return {"benchmark": "server_memory", "models": served, "small_requests": small_requests,
            "small_points": SMALL_POINTS, "searched": searches, "big_points": big_points, "seed": seed,
            "rss_mib": {k: round(v, 1) for k, v in rss.items()}, "machine": machine_info(THREADS)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", help="serve only these model names, comma separated (default: every bundled one)")
    parser.add_argument("--small", type=positive_int, default=5, help="1,024-point registrations before the big one")
    parser.add_argument("--big-points", type=positive_int, default=100_000,
                        help="points per cloud of the big JSON request")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    if args.models:
        from service.manifest import discover_model_dirs

        bundled = [folder.name for folder in discover_model_dirs([])]
        unknown = [name for name in args.models.split(",") if name.strip() not in bundled]
        if unknown:
            parser.error(f"--models: no bundled model {', '.join(unknown)} (bundled: {', '.join(bundled)})")
    checked(require_shapes, "test", "dense", None)  # the requests' pairs
    json_destination(args.json)
    report = measure(args.models, args.small, args.big_points, args.seed)
    emit_report(report, args.json)
    return report


if __name__ == "__main__":
    main()
