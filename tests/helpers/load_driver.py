"""Closed-loop load driver for the registration service (httpx + asyncio), bounded in time and requests.

``--concurrency`` workers each send a registration, wait for the answer, and send the next, until
``--seconds`` have passed or ``--max-requests`` were sent; then it stops by itself. Requests cycle over
seeded ModelNet40 pairs and two routes (``/v1/register`` JSON and OIP v2 ``infer``), their bodies
serialized once up front so the driver spends little CPU. Before the load, one sequential request per
(pair, route) gives the reference transform; under load every 200 must equal it exactly.

Reported (JSON): statuses, errors (anything but 200 and the designed 503; transport errors too),
transforms that differ from the reference, latency p50/p95/p99 of the 200s and of the 503s,
throughput, and the server's RSS (``/proc/<pid>/status``) before and after the load.

Against a running server::

    python tests/helpers/load_driver.py --url http://127.0.0.1:8080 --pid 1234 --seconds 60 --concurrency 8

or let it start one (a verified copy of the bundled model; ``MFGNET_*`` settings from the flags)::

    python tests/helpers/load_driver.py --seconds 180 --concurrency 16 --max-concurrency 2 --max-queue 4 \\
        --out load.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from api_server import MODEL, modelnet_pair  # a script as well as a module of the tests

ROUTES = ("/v1/register", f"/v2/models/{MODEL}/infer")
DESIGNED = {200, 503}  # 503: the bounded queue refusing work, by design


@dataclass
class Job:
    route: str
    seed: int
    content: bytes


@dataclass
class Report:
    url: str
    seconds: float
    concurrency: int
    options: dict
    requests: int = 0
    statuses: dict[str, int] = field(default_factory=dict)
    errors: int = 0  # statuses outside DESIGNED, plus transport errors
    transport_errors: dict[str, int] = field(default_factory=dict)
    transport_error_samples: list[str] = field(default_factory=list)  # the first few, with the time into the run
    mismatches: int = 0  # 200s whose transform differs from the sequential reference
    throughput_rps: float = 0.0
    ok_rps: float = 0.0
    latency_ms: dict[str, float] = field(default_factory=dict)  # of the 200s
    latency_503_ms: dict[str, float] = field(default_factory=dict)
    rss_kib: dict[str, int | None] = field(default_factory=dict)
    rss_timeline_kib: list[list[float]] = field(default_factory=list)  # [seconds into the run, RSS]
    elapsed_s: float = 0.0
    date: str = ""


def build_jobs(seeds: list[int], points: int | None, options: dict) -> list[Job]:
    jobs = []
    for seed in seeds:
        pair = modelnet_pair(seed)
        source, target = pair.source[:points], pair.target[:points]
        body = {"source": source.tolist(), "target": target.tolist(), **options}
        jobs.append(Job(ROUTES[0], seed, json.dumps(body).encode()))
        infer = {
            "id": f"seed-{seed}",
            "parameters": options,
            "inputs": [
                {"name": "SOURCE", "shape": list(source.shape), "datatype": "FP32", "data": source.ravel().tolist()},
                {"name": "TARGET", "shape": list(target.shape), "datatype": "FP32", "data": target.ravel().tolist()},
            ],
        }
        jobs.append(Job(ROUTES[1], seed, json.dumps(infer).encode()))
    return jobs


def transform_of(route: str, body: dict) -> list:
    if route == ROUTES[0]:
        return body["transform"]
    return next(o for o in body["outputs"] if o["name"] == "TRANSFORM")["data"]


def rss_kib(pid: int | None, key: str = "VmRSS") -> int | None:
    if pid is None:
        return None
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    match = re.search(rf"^{key}:\s+(\d+) kB", text, re.MULTILINE)
    return int(match.group(1)) if match else None


def percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"p50": round(float(p50), 1), "p95": round(float(p95), 1), "p99": round(float(p99), 1),
            "max": round(max(values), 1), "count": len(values)}


async def drive(
    url: str,
    seconds: float,
    concurrency: int,
    max_requests: int = 100_000,
    pid: int | None = None,
    seeds: tuple[int, ...] = (1, 2, 3, 4),
    points: int | None = None,
    options: dict | None = None,
    headers: dict | None = None,
    backoff_s: float = 0.05,
    timeout_s: float = 60.0,
    rss_every_s: float = 10.0,
) -> Report:
    """Load ``url`` for ``seconds`` (or ``max_requests``) with ``concurrency`` closed-loop workers."""
    options = dict(options or {})
    jobs = build_jobs(list(seeds), points, options)
    report = Report(url, seconds, concurrency, options)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(base_url=url, timeout=timeout_s, limits=limits, headers=headers or {},
                                 verify=False) as client:
        send_headers = {"content-type": "application/json"}
        reference = {}
        for job in jobs:  # sequential references (and the warm-up)
            response = await client.post(job.route, content=job.content, headers=send_headers)
            response.raise_for_status()
            reference[job.route, job.seed] = transform_of(job.route, response.json())
        report.rss_kib["before"] = rss_kib(pid)

        statuses: Counter[str] = Counter()
        transport: Counter[str] = Counter()
        latency: dict[int, list[float]] = {200: [], 503: []}
        sent = 0
        started = time.perf_counter()
        deadline = started + seconds

        async def worker(index: int) -> None:
            nonlocal sent
            i = index
            while time.perf_counter() < deadline and sent < max_requests:
                sent += 1
                job = jobs[i % len(jobs)]
                i += concurrency
                t0 = time.perf_counter()
                try:
                    response = await client.post(job.route, content=job.content, headers=send_headers)
                except httpx.HTTPError as exc:
                    transport[type(exc).__name__] += 1
                    if len(report.transport_error_samples) < 5:
                        at = time.perf_counter() - started
                        report.transport_error_samples.append(f"{at:.1f} s: {type(exc).__name__}: {exc!r}"[:300])
                    continue
                ms = 1000 * (time.perf_counter() - t0)
                statuses[str(response.status_code)] += 1
                if response.status_code in latency:
                    latency[response.status_code].append(ms)
                if response.status_code == 200:
                    if transform_of(job.route, response.json()) != reference[job.route, job.seed]:
                        report.mismatches += 1
                elif response.status_code == 503:
                    await asyncio.sleep(backoff_s)  # a polite client; Retry-After says 1 s

        async def sample_rss() -> None:
            while time.perf_counter() < deadline and sent < max_requests:
                report.rss_timeline_kib.append([round(time.perf_counter() - started, 1), rss_kib(pid)])
                await asyncio.sleep(rss_every_s)

        sampler = asyncio.create_task(sample_rss())
        await asyncio.gather(*(worker(k) for k in range(concurrency)))
        sampler.cancel()
        report.elapsed_s = round(time.perf_counter() - started, 2)
        report.rss_kib["after"] = rss_kib(pid)
        report.rss_kib["peak"] = rss_kib(pid, "VmHWM")

    report.requests = sum(statuses.values()) + sum(transport.values())
    report.statuses = dict(sorted(statuses.items()))
    report.transport_errors = dict(transport)
    report.errors = sum(n for s, n in statuses.items() if int(s) not in DESIGNED) + sum(transport.values())
    report.throughput_rps = round(report.requests / report.elapsed_s, 2)
    report.ok_rps = round(statuses.get("200", 0) / report.elapsed_s, 2)
    report.latency_ms = percentiles(latency[200])
    report.latency_503_ms = percentiles(latency[503])
    report.date = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="a running server; without it one is started (and stopped) here")
    parser.add_argument("--pid", type=int, help="server process id, for RSS (found by itself when it starts one)")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--max-requests", type=int, default=100_000)
    parser.add_argument("--points", type=int, help="points per cloud (default: the pairs' 700)")
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--keypoints", type=int)
    parser.add_argument("--api-key")
    parser.add_argument("--max-concurrency", type=int, default=2, help="MFGNET_MAX_CONCURRENCY of a started server")
    parser.add_argument("--max-queue", type=int, default=4, help="MFGNET_MAX_QUEUE of a started server")
    parser.add_argument("--threads", type=int, default=1, help="MFGNET_THREADS of a started server")
    parser.add_argument("--out", help="write the JSON report here (it is printed either way)")
    parser.add_argument("--server-log", help="copy the started server's JSON log here")
    args = parser.parse_args(argv)

    options = {k: v for k, v in (("iterations", args.iterations), ("keypoints", args.keypoints)) if v is not None}
    headers = {"Authorization": f"Bearer {args.api_key}"} if args.api_key else None
    server = None
    url, pid = args.url, args.pid
    if url is None:
        from api_server import start_subprocess_server

        server = start_subprocess_server(
            "load", MFGNET_MAX_CONCURRENCY=str(args.max_concurrency), MFGNET_MAX_QUEUE=str(args.max_queue),
            MFGNET_THREADS=str(args.threads),
        )
        url, pid = server.url, server.extra["proc"].pid
    try:
        report = asyncio.run(drive(url, args.seconds, args.concurrency, args.max_requests, pid,
                                   points=args.points, options=options, headers=headers))
    finally:
        if server is not None:
            server.stop()
            if args.server_log:
                Path(args.server_log).write_bytes(server.log_path.read_bytes())
    out = asdict(report)
    out["command"] = " ".join([os.path.basename(sys.argv[0]), *(argv if argv is not None else sys.argv[1:])])
    if server is not None:
        out["server"] = {"max_concurrency": args.max_concurrency, "max_queue": args.max_queue, "threads": args.threads}
    text = json.dumps(out, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0 if report.errors == 0 and report.mismatches == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
