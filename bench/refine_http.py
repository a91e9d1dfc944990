"""HTTP latency of a request that names no refinement (the server's default) against ``"refine": "none"``.

``python -m bench.refine_http --pairs dense.npz --pairs resampled.npz [--count 20] [--json out.json]``
starts the service (``bench.http_latency.Server``) on 127.0.0.1, sends each pair's JSON body (naming the
model) twice per round
in alternating order (default, then none, or the reverse), and prints the client's p50 / p95 and the
server's own ``timing_ms.total`` p50 per file and request kind.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import httpx
import numpy as np

from bench.http_latency import Server
from bench.report_io import emit_report, json_destination, npz_arrays, positive_int
from service.manifest import discover_model_dirs


def measure(client: httpx.Client, pairs: dict, model: str, count: int, rounds: int) -> dict:
    """Client ms and server ``timing_ms.total`` per request kind, alternating kinds pair by pair."""
    sources, targets = pairs["source"][:count], pairs["target"][:count]
    bodies = [{"source": s.tolist(), "target": t.tolist(), "model": model}
              for s, t in zip(sources, targets, strict=True)]
    client_ms: dict[str, list[float]] = {"default": [], "none": []}
    server_ms: dict[str, list[float]] = {"default": [], "none": []}
    for _ in range(rounds):
        for i, body in enumerate(bodies):
            for kind in ("default", "none") if i % 2 == 0 else ("none", "default"):
                sent = body if kind == "default" else {**body, "refine": "none"}
                tic = time.perf_counter()
                response = client.post("/v1/register", json=sent)
                client_ms[kind].append(1000 * (time.perf_counter() - tic))
                response.raise_for_status()
                server_ms[kind].append(response.json()["timing_ms"]["total"])
    return {
        kind: {
            "http_p50_ms": float(np.median(client_ms[kind])),
            "http_p95_ms": float(np.percentile(client_ms[kind], 95)),
            "server_total_p50_ms": float(np.median(server_ms[kind])),
            "requests": len(client_ms[kind]),
        }
        for kind in client_ms
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=Path, action="append", required=True, help="pairs file (mfgnet make-pairs)")
    parser.add_argument("--model", default="general", help="a bundled model's name (the server serves those)")
    parser.add_argument("--count", type=positive_int, default=20, help="pairs per file")
    parser.add_argument("--rounds", type=positive_int, default=2)
    parser.add_argument("--json", type=Path, default=None, help="write the report here")
    args = parser.parse_args(argv)
    pairs = {path: npz_arrays(parser, path) for path in args.pairs}
    bundled = [folder.name for folder in discover_model_dirs([])]
    if args.model not in bundled:
        parser.error(f"--model {args.model}: not a bundled model (bundled: {', '.join(bundled)})")
    json_destination(args.json)

    with Server(threads=2) as server, httpx.Client(base_url=server.url, timeout=120) as client:
        report = {
            "date": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
            "model": args.model,
            "results": {
                path.stem: measure(client, pairs[path], args.model, args.count, args.rounds)
                for path in args.pairs
            },
        }
    emit_report(report, args.json)


if __name__ == "__main__":
    main()
