"""Throughput and latency under concurrent requests: this checkout's server against another checkout's, or
against itself with other thread settings::

    python -m bench.load --pairs pairs_dense.npz --compare-root /tmp/old-checkout --json load.json
    python -m bench.load --pairs pairs_dense.npz --settings 2x2 --settings 1x2 --settings 1x4

Every server (a real uvicorn process on 127.0.0.1, :class:`bench.http_latency.Server`) serves its bundled
models and gets the same registrations (the first ``--bodies`` pairs of the file, the service's default
options) at each client concurrency; the servers take turns, and every round reverses their order, so that a
drift of the machine's speed does not favour one. ``--settings TxC``: ONNX Runtime threads per session x
registrations at once (``MFGNET_THREADS`` x ``MFGNET_MAX_CONCURRENCY``); other checkouts get the first.
"""

from __future__ import annotations

import argparse
import json
import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.http_latency import CONCURRENCY, Server, run_load
from bench.report_io import json_destination, machine_info, npz_arrays, positive_int, provenance, require_checkouts
from service.core.config import Settings


@dataclass(frozen=True)
class ServerSpec:
    root: str | None = None  # a checkout to serve from (None: this one)
    threads: int = 2  # MFGNET_THREADS
    max_concurrency: int = 2  # MFGNET_MAX_CONCURRENCY

    @property
    def name(self) -> str:
        return f"{self.root or '(this checkout)'}, {self.threads}x{self.max_concurrency}"


def parse_setting(text: str) -> tuple[int, int]:
    """``"2x2"`` -> ``(threads, max_concurrency)``."""
    try:
        threads, concurrency = (int(part) for part in text.lower().split("x"))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected THREADSxCONCURRENCY such as 2x2, got {text!r}") from err
    if threads < 1 or concurrency < 1:
        raise argparse.ArgumentTypeError(f"threads and concurrency must be >= 1, got {text!r}")
    return threads, concurrency


def compare_load(pairs: dict[str, np.ndarray], specs: list[ServerSpec], requests: int = 40, rounds: int = 2,
                 concurrency: tuple[int, ...] = CONCURRENCY, bodies: int = 16) -> list[dict]:
    """One ``run_load`` row per (round, client concurrency, server)."""
    payloads = [{"source": s.tolist(), "target": t.tolist()}
                for s, t in zip(pairs["source"][:bodies], pairs["target"][:bodies], strict=True)]
    rows = []
    with ExitStack() as stack:
        servers = [(spec.name, stack.enter_context(Server(threads=spec.threads, max_concurrency=spec.max_concurrency,
                                                          cwd=spec.root)))
                   for spec in specs]
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
    parser.add_argument("--compare-root", action="append", default=[],
                        help="another checkout to serve beside this one")
    parser.add_argument("--requests", type=positive_int, default=40, help="requests per concurrency, server and round")
    parser.add_argument("--rounds", type=positive_int, default=2)
    parser.add_argument("--concurrency", type=positive_int, action="append", help="default: 1, 2, 4, 8")
    parser.add_argument("--settings", type=parse_setting, action="append",
                        help="THREADSxCONCURRENCY of this checkout's server, repeatable (default: 2x2)")
    parser.add_argument("--json", help="also write the rows here")
    args = parser.parse_args(argv)
    pairs = npz_arrays(parser, Path(args.pairs))
    json_destination(args.json)
    require_checkouts(parser, args.compare_root)
    settings = args.settings or [(2, 2)]
    specs = [ServerSpec(None, t, c) for t, c in settings]
    specs += [ServerSpec(root, *settings[0]) for root in args.compare_root]
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    # before the run: the checkout may move on during it; --compare-root servers run their roots' code
    made_by = provenance([Settings().default_model])  # the model a default request gets
    rows = compare_load(pairs, specs, args.requests, args.rounds, tuple(args.concurrency or CONCURRENCY))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"started": started, "pairs": args.pairs, "rows": rows,
                       "machine": machine_info(max(spec.threads for spec in specs)),  # rows: each server's TxC
                       "provenance": made_by}, f, indent=1)


if __name__ == "__main__":
    main()
