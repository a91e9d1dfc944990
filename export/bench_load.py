"""Throughput and latency under concurrent requests, this checkout's server against another checkout's::

    python -m export.bench_load --pairs pairs_dense.npz --compare-root /tmp/old-checkout --json load.json

Both servers (real uvicorn processes on 127.0.0.1, :class:`export.bench_http.Server`) serve their bundled
models and get the same registrations (the first ``--bodies`` pairs of the file, the service's default
options) at each concurrency; the servers take turns, and every round reverses their order, so that a drift of
the machine's speed does not favour one.
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import ExitStack

import numpy as np

from export.bench_http import CONCURRENCY, Server, run_load


def compare_load(pairs: dict[str, np.ndarray], roots: list[str | None], requests: int = 40, rounds: int = 2,
                 concurrency: tuple[int, ...] = CONCURRENCY, bodies: int = 16, threads: int = 2) -> list[dict]:
    """One ``run_load`` row per (round, concurrency, server); ``roots``: checkouts (``None``: this one)."""
    payloads = [{"source": s.tolist(), "target": t.tolist()}
                for s, t in zip(pairs["source"][:bodies], pairs["target"][:bodies], strict=True)]
    rows = []
    with ExitStack() as stack:
        servers = [(root or "(this checkout)", stack.enter_context(Server(threads=threads, cwd=root)))
                   for root in roots]
        for round_ in range(rounds):
            for c in concurrency:
                for name, server in servers if round_ % 2 == 0 else servers[::-1]:
                    row = run_load(server.url, payloads, c, requests)
                    rows.append({"server": name, "round": round_, **row})
                    print(f"{name}: concurrency {c}, {row['throughput_rps']:.1f} req/s, p50 {row['p50_ms']:.1f} ms",
                          flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True, help="pairs .npz (mfgnet make-pairs)")
    parser.add_argument("--compare-root", action="append", default=[], help="another checkout to serve beside this one")
    parser.add_argument("--requests", type=int, default=40, help="requests per concurrency, server and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--concurrency", type=int, action="append", help="default: 1, 2, 4, 8")
    parser.add_argument("--threads", type=int, default=2, help="ONNX Runtime threads of each server")
    parser.add_argument("--json", help="also write the rows here")
    args = parser.parse_args(argv)
    with np.load(args.pairs) as data:
        pairs = {key: data[key] for key in ("source", "target")}
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    rows = compare_load(pairs, [None, *args.compare_root], args.requests, args.rounds,
                        tuple(args.concurrency or CONCURRENCY), threads=args.threads)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"started": started, "pairs": args.pairs, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
